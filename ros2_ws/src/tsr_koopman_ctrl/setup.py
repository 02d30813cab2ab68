from glob import glob

from setuptools import find_packages, setup

package_name = 'tsr_koopman_ctrl'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='tsr-koopman',
    maintainer_email='tsr-koopman@example.com',
    description='Tension control of TSR deployment and the MCAP bag recorder.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'controller_node = tsr_koopman_ctrl.controller_node:main',
            'recorder_node = tsr_koopman_ctrl.recorder_node:main',
            'deploy = tsr_koopman_ctrl.deploy:main',
        ],
    },
)
