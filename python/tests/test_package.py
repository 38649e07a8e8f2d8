"""The package: version, adapters, docstrings and their examples, type stubs."""

import doctest
import pathlib
import re

import stickslip
from systems import REQUIRE_GPU

ROOT = pathlib.Path(__file__).resolve().parents[2]


def cargo_version(path):
    text = path.read_text()
    package = text.split("[package]", 1)[1]
    return re.search(r'^version\s*=\s*"([^"]+)"', package, re.M).group(1)


def test_version_equals_the_crates():
    assert stickslip.__version__ == cargo_version(ROOT / "Cargo.toml")
    assert stickslip.__version__ == cargo_version(ROOT / "python" / "Cargo.toml")


def test_adapters_lists_what_stickslip_info_lists():
    found = stickslip.adapters()
    assert isinstance(found, list)
    for a in found:
        assert isinstance(a["name"], str) and a["name"]
        assert isinstance(a["shader_f64"], bool)
        assert a["max_buffer_size"] > 0
    if REQUIRE_GPU:
        assert found, "no GPU adapter and STICKSLIP_REQUIRE_GPU=1"


def test_docstring_examples_run():
    result = doctest.testmod(stickslip, raise_on_error=False)
    assert result.attempted >= 2 and result.failed == 0


def test_public_names_are_documented():
    for name in stickslip.__all__:
        if name.startswith("__"):
            continue
        obj = getattr(stickslip, name)
        assert obj.__doc__ and len(obj.__doc__.strip()) > 20, name
    assert stickslip.Solver.solve.__doc__


def test_stubs_and_marker_are_installed():
    pkg = pathlib.Path(stickslip.__file__).parent
    assert (pkg / "py.typed").exists()
    stub = (pkg / "__init__.pyi").read_text()
    for name in stickslip.__all__:
        if not name.startswith("__"):
            assert re.search(rf"^(def|class) {name}\b", stub, re.M), name
