from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'tsr_koopman_ctrl'


def model_files():
    """Every shipped model directory under models/ (a link to the repository's models/),
    installed to share/<pkg>/models/<same path>, so nodes find them from any directory."""
    entries = []
    for directory, _, names in os.walk('models', followlinks=True):
        files = [os.path.join(directory, n) for n in sorted(names)
                 if n in ('model.json', 'weights.safetensors', 'README.md')]
        if files:
            entries.append((os.path.join('share', package_name, directory), files))
    return entries


setup(
    name=package_name,
    version='0.2.0',
    packages=find_packages(exclude=['test']),
    # The frontier table evaluation/frontier.py reads next to itself.
    package_data={package_name: ['evaluation/frontier_table.json']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        *model_files(),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='tsr-koopman',
    maintainer_email='tsr-koopman@example.com',
    description='Koopman-model tension control of tethered space robot deployment: control '
                'laws, learning, bags, the controller and recorder nodes, the deployment API '
                'and its commands.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'controller_node = tsr_koopman_ctrl.nodes.controller_node:main',
            'recorder_node = tsr_koopman_ctrl.nodes.recorder_node:main',
            'deploy = tsr_koopman_ctrl.commands.deploy:main',
            'train = tsr_koopman_ctrl.commands.train:main',
            'retrain = tsr_koopman_ctrl.commands.retrain:main',
            'bag = tsr_koopman_ctrl.commands.bag:main',
            'config = tsr_koopman_ctrl.commands.config:main',
            'campaign = tsr_koopman_ctrl.commands.campaign:main',
        ],
    },
)
