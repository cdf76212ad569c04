"""One base for mrrig's ordinary errors (`MrrigError`), each message one line, and no error
named after a builtin."""

from __future__ import annotations

import builtins
import importlib
import inspect
import pkgutil

import pytest

import damper
import firmware_sim
import mrrig
from mrrig.errors import MrrigError

# Exceptions that are signals between parts of one tool, not errors shown to anyone.
SIGNALS = {"mrrig.rigio.rig_session.Interrupted", "mrrig.interruption.Interrupted"}


def _exception_classes() -> list[type[BaseException]]:
    found = []
    for pkg in (mrrig, firmware_sim, damper):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            # alembic's env.py is a script alembic runs with its context set, not a module
            if info.name.endswith("__main__") or info.name == "mrrig.catalog.migrations.env":
                continue
            module = importlib.import_module(info.name)
            for _, obj in inspect.getmembers(module, inspect.isclass):
                if issubclass(obj, BaseException) and obj.__module__ == info.name:
                    found.append(obj)
    return found


ERRORS = _exception_classes()


def test_every_error_of_the_project_derives_from_mrrig_error() -> None:
    names = {f"{e.__module__}.{e.__qualname__}" for e in ERRORS}
    assert {"mrrig.typed_config.ConfigError", "mrrig.rigio.control.RequestError"} <= names
    loose = sorted(
        n
        for e, n in ((e, f"{e.__module__}.{e.__qualname__}") for e in ERRORS)
        if not issubclass(e, MrrigError) and n not in SIGNALS
    )
    assert loose == []


def test_no_error_is_named_after_a_builtin() -> None:
    shadowing = [
        f"{e.__module__}.{e.__qualname__}" for e in ERRORS if hasattr(builtins, e.__name__)
    ]
    assert shadowing == []


@pytest.mark.parametrize("error", [e for e in ERRORS if issubclass(e, MrrigError)], ids=str)
def test_an_error_message_given_on_several_lines_reads_as_one(error) -> None:
    text = str(error("configs/rig.toml: loop.i_max_a:\n  expected a number,\n\ngot 'two'"))
    assert text == "configs/rig.toml: loop.i_max_a: expected a number, got 'two'"
