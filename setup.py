"""vmocap: markerless multi-camera motion capture as a ROS 2 (Jazzy) node graph."""

from glob import glob

from setuptools import find_packages, setup

package_name = "vmocap"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["vmocap_core", "vmocap_core.*", "vmocap_ros", "vmocap_ros.*"]),
    package_data={"vmocap_core": ["data/motions/*.npz", "data/motions/*.md", "data/pcm/*.json", "data/pcm/*.jpg", "data/pcm/*.md", "data/landmarks/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*")),
        ("share/" + package_name + "/launch", glob("launch/*")),
    ],
    install_requires=["numpy", "opencv-python-headless", "onnxruntime", "pin", "mcap", "scipy", "tqdm", "matplotlib", "pyyaml"],
    # OpenSim's Python API (reads our TRC in the export tests; scripts/setup.sh installs it)
    extras_require={"opensim": ["opensim==4.6"]},
    python_requires=">=3.11",
    zip_safe=False,
    maintainer="vmocap developers",
    maintainer_email="vmocap@localhost",
    description="Markerless video motion capture from part confidence maps (Ohashi et al.) for ROS 2",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={"console_scripts": ["vmocap = vmocap_core.cli:main"]},
)
