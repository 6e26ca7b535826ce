"""The package is a ROS 2 ament_python package: colcon builds it and installs what ROS expects."""
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_package_xml_is_format_3_with_runtime_dependencies():
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "multi_instance_reg"
    deps = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "sensor_msgs", "geometry_msgs", "visualization_msgs", "std_msgs"} <= deps
    assert root.find("export/build_type").text == "ament_python"


def test_colcon_build_installs_the_ros_layout(tmp_path):
    colcon = Path(sys.executable).with_name("colcon")
    assert colcon.exists(), "colcon is pinned in requirements.txt; run `make test` to install it"
    src = tmp_path / "ws" / "src" / "multi_instance_reg"
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    for rel in files:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, src / rel)
    p = subprocess.run([str(colcon), "build", "--event-handlers", "console_direct-"], cwd=tmp_path / "ws",
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    install = tmp_path / "ws" / "install" / "multi_instance_reg"
    share = install / "share" / "multi_instance_reg"
    assert (install / "share" / "ament_index" / "resource_index" / "packages" / "multi_instance_reg").exists()
    assert (share / "package.xml").exists()
    assert sorted(p.name for p in (share / "config").glob("*.yaml")) == sorted(p.name for p in (ROOT / "config").glob("*.yaml"))
    assert sorted(p.name for p in (share / "launch").glob("*.py")) == sorted(p.name for p in (ROOT / "launch").glob("*.py"))
    # `ros2 run multi_instance_reg <exe>` looks in lib/<package>.
    assert (install / "lib" / "multi_instance_reg" / "mireg").exists()
    # The Fast DDS profile travels with the Python package (ros/transport.py finds it there).
    assert list(install.glob("lib/python*/site-packages/multi_instance_reg/ros/fastdds_large_data.xml"))
    # Every package folder of the source is installed (setup.py's find_packages: by its __init__.py).
    site = next(install.glob("lib/python*/site-packages"))
    packages = sorted(p.parent.relative_to(ROOT) for p in (ROOT / "multi_instance_reg").rglob("__init__.py"))
    assert [p for p in packages if not (site / p / "__init__.py").exists()] == []
