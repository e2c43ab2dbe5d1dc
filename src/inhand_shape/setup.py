from setuptools import find_packages, setup

package_name = 'inhand_shape'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='In-hand mapping maintainers',
    maintainer_email='maintainers@inhand-mapping.org',
    description='Shape from the map: surface mesh, superquadric parts, graspable part and grasps.',
    license='Apache-2.0',
    entry_points={'console_scripts': []},
)
