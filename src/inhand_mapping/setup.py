from setuptools import find_packages, setup

package_name = 'inhand_mapping'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['cell_judge_model.npz']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='In-hand mapping maintainers',
    maintainer_email='maintainers@inhand-mapping.org',
    description='Registration, probabilistic occupancy mapping and map building from bags.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'registration_node = inhand_mapping.nodes.registration_node:main',
            'occupancy_node = inhand_mapping.nodes.occupancy_node:main',
            'shape_node = inhand_mapping.nodes.shape_node:main',
            'exploration_node = inhand_mapping.nodes.exploration_node:main',
        ],
    },
)
