from glob import glob

from setuptools import find_packages, setup

package_name = 'tsr_sim'

setup(
    name=package_name,
    version='0.2.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/config/plants', glob('config/plants/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='tsr-koopman',
    maintainer_email='tsr-koopman@example.com',
    description='Tethered space robot deployment plant and simulator node.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'sim_node = tsr_sim.sim_node:main',
        ],
    },
)
