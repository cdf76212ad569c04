"""Issue 32, finding 13 (the control plane's and the config's part): a value that no field can
take is refused with one line naming the field, not with Python's words from deeper down."""

from __future__ import annotations

import pytest

from mrrig.config import load_config
from mrrig.rigio.control import RequestError, parse_request
from mrrig.typed_config import ConfigError


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        (
            '{"cmd": "set_profile", "kind": "constant", "offset_n": 1' + "0" * 400 + "}",
            "offset_n: an integer of 401 digits is beyond a float's range",
        ),
        (
            '{"cmd": "set_profile", "kind": "csv", "path": "profiles/a\\u0000.csv"}',
            "path: contains a NUL character (\\u0000)",
        ),
        (
            '{"cmd": "set_model", "path": "models/\\ud800.json"}',
            "path: a lone surrogate \\ud800 is not text",
        ),
        (
            '{"cmd": "set_controller", "name": "constant", "x": {"\\u0000": 1}}',
            "x.\x00 (the key): contains a NUL character",
        ),
    ],
)
def test_finding13_a_request_value_no_field_can_take_is_named(raw, expected):
    with pytest.raises(RequestError) as err:
        parse_request(raw.encode())
    assert str(err.value).startswith(expected), str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('[recording]\ndirectory = "rec\\u0000ordings"\n', "recording.directory: contains a NUL"),
        ("[loop]\ni_max_a = 1" + "0" * 400 + "\n", "loop.i_max_a: expected a number, got an"),
    ],
)
def test_finding13_a_config_value_no_field_can_take_is_named(tmp_path, text, expected):
    path = tmp_path / "rig.toml"
    path.write_text('[bus]\ninterface = "virtual"\nchannel = "x"\n' + text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert f"{path}: {expected}" in str(err.value), str(err.value)
