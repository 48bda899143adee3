"""Build of the one optional C extension (everything else is in pyproject.toml).

ev3dgs.io.aedat4._fast reads AEDAT 4.0 events packets in C (see ev3dgs/io/aedat4_fast.py). It is optional: where
no C compiler is found the install still succeeds and the readers use their numpy path (slower, same results).
"""
from setuptools import Extension, setup

setup(ext_modules=[Extension("ev3dgs.io.aedat4._fast", ["ev3dgs/io/aedat4/_fast.c"], optional=True,
                             extra_compile_args=["-O3", "-std=c11", "-pthread", "-Wall", "-Wextra"],
                             extra_link_args=["-pthread"])])
