from glob import glob

from setuptools import find_packages, setup

package_name = "afm_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(
        exclude=["test", "benchmarks", "benchmarks.*"]
    ),  # benchmarks/ is not installed
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/config/samples", glob("config/samples/*.yaml")),
        ("share/" + package_name + "/config/datasets", glob("config/datasets/*.yaml")),
        ("share/" + package_name + "/config/foxglove", glob("config/foxglove/*.json")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    package_data={"afm_ros.formats": ["nanonis_catalog.json"]},
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="afm_ros developers",
    maintainer_email="afm_ros@example.org",
    description="Tapping-mode AFM instrument emulator for ROS 2 Jazzy",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "cantilever_node = afm_ros.nodes.cantilever_node:main",
            "lockin_node = afm_ros.nodes.lockin_node:main",
            "z_controller_node = afm_ros.nodes.z_controller_node:main",
            "pll_node = afm_ros.nodes.pll_node:main",
            "afm_instrument = afm_ros.tools.afm_instrument:main",
            "recorder_node = afm_ros.nodes.recorder_node:main",
            "replay_node = afm_ros.nodes.replay_node:main",
            "scanner_node = afm_ros.nodes.scanner_node:main",
            "live_view_node = afm_ros.nodes.live_view_node:main",
            "afm_study = afm_ros.tools.study:main",
            "afm_report = afm_ros.tools.report:main",
            "afm_ctl = afm_ros.tools.afm_ctl:main",
            "nanonis_node = afm_ros.tools.nanonis_node:main",
            "bimodal_node = afm_ros.nodes.bimodal_node:main",
        ],
    },
)
