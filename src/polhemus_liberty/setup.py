from setuptools import find_packages, setup

package_name = 'polhemus_liberty'

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
    description='Polhemus Liberty driver node and device emulator.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'liberty_driver = polhemus_liberty.nodes.liberty_driver:main',
            'liberty_emulator = polhemus_liberty.commands.liberty_emulator:main',
        ],
    },
)
