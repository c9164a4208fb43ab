"""Install metadata: pip (also Debian bookworm's stock pip 23.0.1) installs through PEP 517/660 from pyproject.toml,
not the legacy `setup.py develop` that setup.cfg's [develop] section breaks; package.xml names every Python
dependency of setup.py and only ROS packages the code uses; setup.py ships no folder that does not exist."""

from __future__ import annotations

import ast
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _setup_kwargs() -> dict:
    call = next(n for n in ast.walk(ast.parse((REPO / "setup.py").read_text()))
                if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    return {k.arg: k.value for k in call.keywords}


def test_pip_builds_through_pep517():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    build = tomllib.loads((REPO / "pyproject.toml").read_text())["build-system"]
    assert build["build-backend"] == "setuptools.build_meta"


def test_package_xml_names_what_setup_py_needs_and_only_used_ros_packages():
    deps = [e.text for e in ET.parse(REPO / "package.xml").getroot().iter("exec_depend")]
    for req in ast.literal_eval(_setup_kwargs()["install_requires"]):
        name = re.split(r"[<>=]", req)[0].lower().replace("opencv-python-headless", "opencv").replace("pyyaml",
                                                                                                     "yaml")
        name = {"torch": "pytorch"}.get(name, name)
        assert f"python3-{name}" in deps or f"python3-{name}-pip" in deps, req
    code = " ".join(p.read_text() for p in [*REPO.glob("vi3_ros/**/*.py"), *REPO.glob("msg_adapters/**/*.py"),
                                            *REPO.glob("launch/*.py")])
    for dep in deps:
        if not dep.startswith("python3-") and dep not in ("launch", "launch_ros"):
            assert dep in code, f"package.xml depends on {dep}, which nothing uses"


def test_setup_py_ships_only_existing_folders():
    package_data = _setup_kwargs().get("package_data")
    for package, patterns in (ast.literal_eval(package_data).items() if package_data is not None else ()):
        for pattern in patterns:
            assert list((REPO / package).glob(pattern)), (package, pattern)
