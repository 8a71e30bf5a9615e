"""Units of the nirspi sweeper that the CLI tests cannot force."""

from __future__ import annotations

from hydra.core.override_parser.overrides_parser import OverridesParser

from nirspi_pipe.sweeper import subdir_override


def test_hex_job_keys_stay_strings() -> None:
    # An unquoted 4703e54460190101 parses as the float inf: two jobs then shared a folder.
    for key in ("4703e54460190101", "0000000000000001", "1e10aaaaaaaaaaaa", "deadbeefdeadbeef"):
        (ov,) = OverridesParser.create().parse_overrides([subdir_override(key)])
        value = ov.value()
        assert isinstance(value, str) and value == key
