"""A bad number or output path on the command line stops the command at parsing: exit 2 and
one line naming the flag, before a bus, a process or a training run starts."""

from __future__ import annotations

import pytest

from mrrig.cli.main import main
from mrrig.cli_args import output_file

CASES = [
    (["bench", "paper", "--epochs", "-3"], "argument --epochs: must be >= 1, got -3"),
    (["bench", "matrix", "--seed", "-1"], "argument --seed: must be >= 0, got -1"),
    (["bench", "inversion", "--continuity", "-1"], "argument --continuity: must be >= 0, got -1"),
    (["bench", "estimation", "--duration-s", "0"], "argument --duration-s: must be > 0, got 0"),
    (["bench", "loop", "--duration", "nan"], "argument --duration: must be finite, got nan"),
    (["demo", "--duration", "-20"], "argument --duration: must be > 0, got -20"),
    (["run", "--config", "rig.toml", "--duration", "0"], "argument --duration: must be > 0"),
    (["sim", "--duration", "inf"], "argument --duration: must be finite, got inf"),
    (["bridge", "--port", "70000"], "argument --port: must be <= 65535, got 70000"),
    (["train", "d.csv", "--n-train", "0"], "argument --n-train: must be >= 1, got 0"),
    (["train", "d.csv", "--epochs", "ten"], "argument --epochs: expected an integer, got 'ten'"),
    (["train", "d.csv", "--i-max", "-2"], "argument --i-max: must be > 0, got -2"),
    (["train", "d.csv", "--holdout-fraction", "0.7"], "--holdout-fraction: must be < 0.5, got 0.7"),
    (["train", "d.csv", "--hidden", "0"], "argument --hidden: must be >= 1, got 0"),
    (["evaluate", "m.json", "d.csv", "--window", "2,1"], "argument --window: expected START,END"),
    (["bench", "train", "--epochs", "0"], "argument --epochs: must be >= 1, got 0"),
    (["validate", "m.json", "--settle", "-1"], "argument --settle: must be >= 0, got -1"),
    (["send-force", "--sine", "0", "100", "inf"], "argument --sine: must be finite, got inf"),
    (["send-force", "--csv", "p.csv", "--rate", "0"], "argument --rate: must be > 0, got 0"),
    (["watch", "--timeout", "-1"], "argument --timeout: must be > 0, got -1"),
]


@pytest.mark.parametrize(("argv", "expected"), CASES, ids=[" ".join(a) for a, _ in CASES])
def test_a_bad_number_stops_the_command_with_one_line(argv, expected, capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert expected in err[-1], err
    assert "Traceback" not in "\n".join(err)


def test_an_output_file_gets_its_folder_before_the_work(tmp_path) -> None:
    out = tmp_path / "results" / "run1" / "metrics.json"
    assert output_file(str(out)) == out
    assert out.parent.is_dir() and not out.exists()


def test_an_output_that_cannot_be_written_stops_the_command_at_parsing(tmp_path, capsys) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for out, expected in [
        (tmp_path, "is a folder, not a file"),
        (blocker / "metrics.json", f"cannot make the folder {blocker}"),
    ]:
        # the recording does not exist: the output is checked first, before any reading
        with pytest.raises(SystemExit) as stop:
            main(["review", str(tmp_path / "none.rrd"), "--json", str(out)])
        assert stop.value.code == 2
        assert expected in capsys.readouterr().err.strip().splitlines()[-1]
