"""The package list, which pyproject.toml cannot state: ``packages.find`` discovers only folders under their own
name, and the top-level ``configs/`` is shipped as ``torchrl_wbrm.configs``. Everything else is in pyproject.toml."""
from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["torchrl_wbrm", "torchrl_wbrm.*"]), "torchrl_wbrm.configs"],
    package_dir={"torchrl_wbrm.configs": "configs"},
)
