"""Packages whose public names load on first use (gst.lazy): every exported name resolves, and
the modules that extraction's worker processes unpickle stay free of torch."""

import importlib
import subprocess
import sys

import pytest

from gst.lazy import lazy_exports

LAZY = ["gst.data", "gst.data.extract"]


@pytest.mark.parametrize("name", LAZY)
def test_every_exported_name_resolves_and_is_listed(name):
    package = importlib.import_module(name)
    for export in package.__all__:
        assert getattr(package, export) is not None, export
    assert set(package.__all__) <= set(dir(package))
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        package.not_a_name  # noqa: B018


def test_a_package_without_a_type_checking_block_is_refused(tmp_path):
    init = tmp_path / "__init__.py"
    init.write_text("from os import path\n")
    with pytest.raises(ImportError, match="TYPE_CHECKING"):
        lazy_exports("nowhere", str(init))


def test_extraction_workers_do_not_import_torch():
    # A spawned worker imports the module of the function it runs, and with it the packages'
    # __init__ files; torch there costs each worker seconds of CPU.
    code = (
        "import sys, gst.data.extract.masks, gst.data.extract.crops; "
        "print(sorted(m for m in ('torch', 'kornia', 'synth') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
