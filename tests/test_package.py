"""The curated `gns` namespace: every name it promises can be reached."""

import importlib

import gns
import pytest


def test_every_public_name_resolves():
    # The torch-based names load lazily from the module that defines them: a name whose module
    # moved would only fail when a user first touches it.
    for name in gns.__all__:
        value = getattr(gns, name)
        assert value is not None, name
        if name in gns._LAZY:
            assert value is getattr(importlib.import_module(gns._LAZY[name]), name), name


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        gns.no_such_name  # noqa: B018
