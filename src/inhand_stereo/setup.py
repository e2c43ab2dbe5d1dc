from setuptools import find_packages, setup

package_name = 'inhand_stereo'

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
    description='Stereo disparity, 3D points, map texture and calibration for the in-hand map.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'stereo_node = inhand_stereo.nodes.stereo_node:main',
            'calibrate_stereo = inhand_stereo.commands.calibrate_stereo:main',
            'calibrate_camera_tracker = inhand_stereo.commands.calibrate_camera_tracker:main',
        ],
    },
)
