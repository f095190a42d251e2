"""The repository layout of design.md section 2: valid ament_python packages, one-way imports."""

from __future__ import annotations

import ast
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

AMENT_PYTHON = ["medc_sim", "medc_agents", "medc_registry"]


@pytest.mark.parametrize("pkg", AMENT_PYTHON)
def test_ament_python_package_is_valid(pkg: str) -> None:
    root = REPO_ROOT / "ros_ws" / "src" / pkg
    tree = ET.parse(root / "package.xml").getroot()
    assert tree.tag == "package" and tree.get("format") == "3"
    assert tree.findtext("name") == pkg
    assert tree.find("export/build_type").text == "ament_python"
    assert (root / "resource" / pkg).is_file(), "ament index marker missing"
    assert (root / "setup.py").is_file() and (root / pkg / "__init__.py").is_file()


def _imported_modules(path: Path) -> set[str]:
    mods: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            mods.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            mods.add(node.module.split(".")[0])
    return mods


def test_training_never_imports_ros_web3_or_nodes() -> None:
    forbidden = {"rclpy", "web3", "medc_sim", "medc_agents", "medc_registry", "medc_interfaces"}
    for path in (REPO_ROOT / "training" / "medc_training").rglob("*.py"):
        bad = _imported_modules(path) & forbidden
        assert not bad, f"{path.relative_to(REPO_ROOT)} imports {sorted(bad)}"
