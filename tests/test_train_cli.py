"""Every output path of every command is checked before any work: a folder where a file is asked for, a file
where a folder is asked for, a path under a file, a folder one cannot write in. Each command is given an
argument that would fail later (an unknown method, a missing file): the error printed must be the output's,
so the output is checked first."""

from __future__ import annotations

from pathlib import Path

import pytest

from magenv.train.cli import main as cli
from magenv.train.cli import output_file, output_folder
from tests.test_bad_input import read_only_folder

# (command line before the output option, the option, whether it names a folder): each with a later error
OUTPUTS = [
    (["compare", "--methods", "nosuch"], "--csv", False),
    (["compare", "--methods", "nosuch"], "--plot", False),
    (["evaluate", "no/such/run"], "--csv", False),
    (["evaluate", "no/such/run"], "--video", False),
    (["simulate", "--scenario", "nosuch"], "--out", False),
    (["plot", "no/such/trial.h5"], "--out", False),
    (["fidelity", "--recordings", "no/such.hdf5", "--methods", "nosuch"], "--csv", False),
    (["fidelity", "--recordings", "no/such.hdf5", "--methods", "nosuch"], "--plot", False),
    (["train", "--config", "no/such.yaml"], "--out", True),
    (["train", "--teacher", "nosuch"], "--out", True),
    (["tune", "--rule", "nosuch"], "--out", True),
    (["demo", "--csv", "x.csv", "--steps", "1"], "--out", True),
    (["demo", "--out", "no/such/run", "--steps", "1"], "--csv", False),
    (["report", "--methods", "nosuch"], "--out", True),
    (["pictures", "--scenario", "nosuch"], "--out", True),
    (["sweep", "no/such/sweep.yaml"], "--out", True),
    (["estimate", "no/such.csv", "--method", "nosuch"], "--out", False),
    (["estimate", "no/such.csv", "--method", "nosuch", "--out", "x.csv"], "--plot", False),
    (["export", "no/such/run"], "--onnx", False),
    (["data", "broad", "--url", "file:///no/such"], "--dest", True),
]


def _name(argv: list[str], option: str, folder: bool) -> str:
    """A name of the kind the option writes."""
    if folder:
        return "out"
    return "out" + {"--plot": ".png", "--video": ".mp4", "--onnx": ".onnx"}.get(
        option, ".png" if argv[0] == "plot" else ".csv"
    )


def _run(tmp_path: Path, capsys, argv: list[str], option: str, path: Path) -> str:
    code = cli([*argv, option, str(path)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith(f"magenv {argv[0]}: error: {option} "), err
    return err


@pytest.mark.parametrize(("argv", "option", "folder"), OUTPUTS, ids=[f"{a[0]} {o}" for a, o, _ in OUTPUTS])
def test_an_output_under_a_file_is_refused_first(argv, option, folder, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("a file")
    name = _name(argv, option, folder)
    assert "is a file, not a folder" in _run(tmp_path, capsys, argv, option, tmp_path / "file" / name)


@pytest.mark.parametrize(("argv", "option", "folder"), OUTPUTS, ids=[f"{a[0]} {o}" for a, o, _ in OUTPUTS])
def test_an_output_of_the_wrong_kind_is_refused_first(argv, option, folder, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if folder:  # an existing file where a folder is asked for
        (tmp_path / "file").write_text("a file")
        assert "is a file, not a folder" in _run(tmp_path, capsys, argv, option, tmp_path / "file")
    else:  # an existing folder where a file is asked for
        assert "is a folder; give a file name" in _run(tmp_path, capsys, argv, option, tmp_path)


@pytest.mark.parametrize(("argv", "option", "folder"), OUTPUTS, ids=[f"{a[0]} {o}" for a, o, _ in OUTPUTS])
def test_an_output_in_a_read_only_folder_is_refused_first(argv, option, folder, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with read_only_folder(tmp_path / "ro") as ro:
        name = _name(argv, option, folder)
        assert "cannot write in" in _run(tmp_path, capsys, argv, option, ro / name)


def test_output_file_names_what_is_written(tmp_path):
    assert output_file(None, "--csv") is None and output_folder(None, "--out") is None
    assert output_file(tmp_path / "a" / "b" / "t.csv", "--csv") == tmp_path / "a" / "b" / "t.csv"
    assert not (tmp_path / "a").exists()  # checked, not made
    assert output_file(tmp_path / "plot", "--plot", (".png", ".pdf")) == tmp_path / "plot.png"
    assert output_file(tmp_path / "plot.PDF", "--plot", (".png", ".pdf")) == tmp_path / "plot.PDF"
    (tmp_path / "kept.csv").write_text("old")
    assert output_file(tmp_path / "kept.csv", "--csv") == tmp_path / "kept.csv"
    assert (tmp_path / "kept.csv").read_text() == "old"  # checking does not touch it
    with pytest.raises(Exception, match=r"--plot must name a \.png, \.pdf file, got .*plot\.gif"):
        output_file(tmp_path / "plot.gif", "--plot", (".png", ".pdf"))
    (tmp_path / "plot.png").mkdir()
    with pytest.raises(Exception, match="is a folder"):
        output_file(tmp_path / "plot", "--plot", (".png",))  # the name it would write is a folder


def test_plot_writes_the_png_it_prints(tmp_path, capsys):
    from tests.conftest import kinematic_trial

    trial = kinematic_trial(duration=1.0).save(tmp_path / "trial.h5")
    assert cli(["plot", str(trial), "--out", str(tmp_path / "drawn")]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "drawn.png")
    assert (tmp_path / "drawn.png").is_file() and not (tmp_path / "drawn").exists()
