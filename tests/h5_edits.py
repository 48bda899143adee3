"""Edits that corrupt one part of an HDF5 scene file, shared by the schema and validation tests.

Each returns fn(f) for an open h5py.File in r+ mode.
"""
from __future__ import annotations


def replace(name, data):
    """Replace dataset `name` by `data` (an array, or a function of the open file)."""
    def fn(f):
        new = data(f) if callable(data) else data
        del f[name]
        f.create_dataset(name, data=new)
    return fn


def set_value(name, value, index=()):
    """Write `value` into dataset `name` at `index` (the whole dataset by default)."""
    def fn(f):
        a = f[name][()]
        a[index] = value
        f[name][...] = a
    return fn


def set_attr(obj, key, value):
    def fn(f):
        f[obj].attrs[key] = value
    return fn
