from glob import glob

from setuptools import find_packages, setup

package_name = 'inhand_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/meshes', sorted(glob('meshes/*.ply'))),
    ],
    install_requires=['setuptools'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='In-hand mapping maintainers',
    maintainer_email='maintainers@inhand-mapping.org',
    description='Simulated in-hand exploration sessions with exact ground truth.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'simulate_session = inhand_sim.commands.simulate_session:main',
            'simulate_pivot = inhand_sim.commands.simulate_pivot:main',
        ],
    },
)
