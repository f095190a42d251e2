from glob import glob

from setuptools import find_packages, setup

PACKAGE = "medc_bringup"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="MEDC developers",
    maintainer_email="dev@medc.invalid",
    description="See package.xml",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "medc-launch = medc_bringup.launcher:main",
            "medc-demo = medc_bringup.demo:main",
            "medc-record = medc_bringup.recorder:main",
            "medc-gas-report = medc_bringup.gas:main",
        ],
        "medc_bench": ["ros = medc_bringup.bench_ros:main"],
    },
)
