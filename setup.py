"""The compiled part of frepvdb: pipeline.io._leafbuild (pipeline/io/leafbuild.cpp), OpenVDB leaves
made in C++ for pipeline.io.vdbgrids.write_batched. Everything else is in pyproject.toml.

It links the system's OpenVDB and boost.python, the ones Debian's python3-openvdb module uses
(.ci/setup.sh installs their headers: libopenvdb-dev, libboost-python-dev). The extension is
optional: where it cannot be built the install goes on and the grids are written with
pyopenvdb's copyFromArray (the same grids, slower); tests/test_leafbuild.py says which is in use."""

import sys

from setuptools import Extension, setup

BOOST_PYTHON = f"boost_python{sys.version_info.major}{sys.version_info.minor}"

setup(ext_modules=[Extension(
    "pipeline.io._leafbuild",
    sources=["pipeline/io/leafbuild.cpp"],
    libraries=["openvdb", BOOST_PYTHON, "tbb"],
    extra_compile_args=["-O2", "-std=c++17", "-Wno-deprecated-declarations"],
    language="c++",
    optional=True,
)])
