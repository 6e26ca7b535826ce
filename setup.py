"""ament_python package: installs with pip into a venv and builds with colcon."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "multi_instance_reg"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={f"{PACKAGE}.ros": ["*.xml"]},   # the Fast DDS profile (ros/transport.py)
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    # Dependencies are pinned in requirements.txt (pip) or come from apt (colcon).
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="multi_instance_reg developers",
    description="Multi-instance 6-DoF registration of a known object in RGB-D with ECC.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "mireg = multi_instance_reg.tools.cli:main",
            "instance_registration_node = multi_instance_reg.ros.node:main",
        ],
    },
)
