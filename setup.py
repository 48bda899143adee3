"""The package list and the one optional C extension (everything else is in pyproject.toml).

Packages are discovered, not listed: every folder under ev3dgs/ is a package, including those that hold only
data (ev3dgs/sim/builtin_scenes has no __init__.py, which plain find_packages would drop), and blender/ installs
as `ev3dgs_blender` (pyproject.toml's package-dir). tests/test_wheel.py compares the wheel with the source tree.

ev3dgs.io.aedat4._fast reads AEDAT 4.0 events packets in C (see ev3dgs/io/aedat4_fast.py). It is optional: where
no C compiler is found the install still succeeds and the readers use their numpy path (slower, same results).
ev3dgs.splat._raster holds the `cpu` rasterizer's SIMD tile kernels (see ev3dgs/splat/cpu_simd.py), optional the
same way: without it the numba kernels run. No -march flag: the AVX2 build inside it is chosen at run time.
"""
from setuptools import Extension, find_namespace_packages, setup

PACKAGES = find_namespace_packages(include=["ev3dgs", "ev3dgs.*"], exclude=["*.__pycache__"]) + ["ev3dgs_blender"]

setup(packages=PACKAGES,
      ext_modules=[Extension("ev3dgs.io.aedat4._fast", ["ev3dgs/io/aedat4/_fast.c"], optional=True,
                             extra_compile_args=["-O3", "-std=c11", "-pthread", "-Wall", "-Wextra"],
                             extra_link_args=["-pthread"]),
                   Extension("ev3dgs.splat._raster", ["ev3dgs/splat/_raster.c"], optional=True,
                             extra_compile_args=["-O3", "-std=gnu11", "-pthread", "-ffp-contract=off", "-Wno-psabi",
                                                 "-Wall", "-Wextra"],
                             extra_link_args=["-pthread"])])
