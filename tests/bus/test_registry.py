"""BackendRegistry: names to lazily imported constructors; an unknown name names its key."""

from __future__ import annotations

from collections import OrderedDict

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus.errors import ConfigError
from services.bus.registry import BackendRegistry


def test_builds_the_named_backend_with_its_options() -> None:
    reg: BackendRegistry[OrderedDict[str, int]] = BackendRegistry(
        "demo.kind", "demo", {"ordered": "collections:OrderedDict", "plain": "builtins:dict"}
    )
    assert reg.names == ("ordered", "plain")
    built = reg.build("ordered", {"a": 1, "b": 2})
    assert isinstance(built, OrderedDict) and list(built.items()) == [("a", 1), ("b", 2)]
    assert reg.load("plain") is dict


def test_an_unknown_name_is_a_config_error_naming_the_key_and_the_choices() -> None:
    reg: BackendRegistry[object] = BackendRegistry("demo.kind", "demo", {"a": "builtins:dict"})
    with pytest.raises(ConfigError) as info:
        reg.build("x" * 10_000, {})
    assert info.value.key == "demo.kind"
    assert "expected one of a" in str(info.value)
    assert len(str(info.value)) < 500  # the bad name is not echoed whole


def test_an_entry_that_is_not_module_colon_class_is_refused_at_declaration() -> None:
    with pytest.raises(ValueError, match="module:Class"):
        BackendRegistry("demo.kind", "demo", {"a": "builtins.dict"})


def test_nothing_is_imported_before_a_backend_is_built() -> None:
    reg: BackendRegistry[object] = BackendRegistry(
        "demo.kind", "demo", {"missing": "services.no_such_module:Thing"}
    )
    assert reg.names == ("missing",)  # declaring did not import it
    with pytest.raises(ModuleNotFoundError):
        reg.load("missing")


@given(st.text(max_size=2000))
def test_any_name_outside_the_registry_is_refused_with_a_bounded_message(name: str) -> None:
    reg: BackendRegistry[object] = BackendRegistry("demo.kind", "demo", {"a": "builtins:dict"})
    if name == "a":
        assert reg.build(name, {}) == {}
        return
    with pytest.raises(ConfigError) as info:
        reg.build(name, {})
    assert info.value.key == "demo.kind"
    assert len(str(info.value)) < 500
