"""ament_python packaging: `colcon build` produces what `ros2 run pisml_ros <node>` executes."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def install_space(tmp_path_factory):
    colcon = shutil.which("colcon", path=str(VENV_BIN)) or shutil.which("colcon")
    if colcon is None:
        pytest.fail("colcon is not installed (scripts/requirements.txt installs it)")
    work = tmp_path_factory.mktemp("colcon")
    env = dict(os.environ, AMENT_PREFIX_PATH=str(Path(sys.prefix)), PATH=f"{VENV_BIN}{os.pathsep}{os.environ['PATH']}")
    proc = subprocess.run([colcon, "build", "--base-paths", str(ROOT), "--packages-select", "pisml_ros",
                           "--build-base", str(work / "build"), "--install-base", str(work / "install")],
                          cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return work / "install" / "pisml_ros"


def test_executables_where_ros2_run_looks(install_space):
    for name in ("measurement", "identifier", "analyser", "gap", "pisml"):
        exe = install_space / "lib" / "pisml_ros" / name
        assert exe.is_file() and os.access(exe, os.X_OK), exe
    assert (install_space / "share" / "ament_index" / "resource_index" / "packages" / "pisml_ros").is_file()
    assert (install_space / "share" / "pisml_ros" / "package.xml").is_file()
    assert (install_space / "share" / "pisml_ros" / "config" / "pisml.yaml").is_file()
    assert (install_space / "share" / "pisml_ros" / "config" / "fastdds_loopback.xml").is_file()
    assert (install_space / "share" / "pisml_ros" / "launch" / "pisml.launch.py").is_file()


def test_installed_code_runs_from_the_install_space(install_space, tmp_path):
    site = next((install_space / "lib").glob("python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    code = "import pisml_ros, sys; print(pisml_ros.__file__)"
    where = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert str(site) in where.stdout, where.stdout + where.stderr
    exe = install_space / "lib" / "pisml_ros" / "pisml"
    proc = subprocess.run([str(exe), "analyse", "--ug", "0.8", "--json"], env=env, capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["stable"] is True


def test_package_manifest_declares_the_real_dependencies():
    text = (ROOT / "package.xml").read_text()
    assert '<package format="3">' in text and "<build_type>ament_python</build_type>" in text
    for dep in ("rclpy", "std_msgs", "diagnostic_msgs", "pisml_msgs", "python3-numpy"):
        assert f">{dep}<" in text
    cfg = (ROOT / "setup.cfg").read_text()
    assert "install_scripts=$base/lib/pisml_ros" in cfg
