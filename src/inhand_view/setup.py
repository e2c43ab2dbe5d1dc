from setuptools import find_packages, setup

package_name = 'inhand_view'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    # the page: plain HTML, JavaScript and CSS, served by the node (no network needed)
    package_data={package_name: ['web/*.html', 'web/*.js', 'web/*.css']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='In-hand mapping maintainers',
    maintainer_email='maintainers@inhand-mapping.org',
    description='The live view: the graph to Foxglove over its WebSocket protocol, and a web page.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'live_view = inhand_view.nodes.live_view:main',
        ],
    },
)
