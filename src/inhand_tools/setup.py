from setuptools import find_packages, setup

package_name = 'inhand_tools'

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
    description='Bag replay/record, topic echo, map metrics and map renders.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'bag_replay = inhand_tools.commands.bag_replay:main',
            'build_map = inhand_tools.commands.build_map:main',
            'compile_kernels = inhand_tools.commands.compile_kernels:main',
            'dds_profile = inhand_tools.commands.dds_profile:main',
            'calibrate_fingertips = inhand_tools.commands.calibrate_fingertips:main',
            'calibrate_vision_model = inhand_tools.commands.calibrate_vision_model:main',
            'bag_record = inhand_tools.commands.bag_record:main',
            'topic_echo = inhand_tools.commands.topic_echo:main',
            'map_metrics = inhand_tools.commands.map_metrics:main',
            'render_map = inhand_tools.commands.render_map:main',
            'extract_shape = inhand_tools.commands.extract_shape:main',
            'predict_surface = inhand_tools.commands.predict_surface:main',
        ],
    },
)
