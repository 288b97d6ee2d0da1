"""Output folders: fitter replaces only what it wrote, and loses nothing at any instant."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from fitter.outdir import MARKER, OutputError, clean_stale, staged_dir


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _write_result(folder, text):
    with open(os.path.join(folder, "result.json"), "w") as fh:
        fh.write(text)


def test_a_folder_of_user_files_is_refused_and_left_whole(tmp_path):
    (tmp_path / "thesis.tex").write_text("years of work")
    (tmp_path / "result.json").write_text("{}")
    with pytest.raises(OutputError, match="did not write.*'thesis.tex'"):
        with staged_dir(str(tmp_path)):
            pytest.fail("the body must not run")
    assert sorted(os.listdir(tmp_path)) == ["result.json", "thesis.tex"]
    assert (tmp_path / "thesis.tex").read_text() == "years of work"


def test_cli_out_dot_in_a_users_folder_exits_2_before_fitting(tmp_path, monkeypatch, capsys):
    from fitter.cli import main

    config = os.path.join(os.path.dirname(__file__), "..", "configs", "quickstart.toml")
    (tmp_path / "notes.csv").write_text("a,b\n1,2\n")
    monkeypatch.chdir(tmp_path)
    code = main(["fit", os.path.abspath(config), "--out", ".", "--no-validate", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert "notes.csv" in err and "Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == ["notes.csv"]


def test_a_fitter_folder_is_replaced_and_carries_the_marker(tmp_path):
    out = tmp_path / "res"
    with staged_dir(str(out)) as tmp:
        _write_result(tmp, "first")
    assert (out / MARKER).is_file() and (out / "result.json").read_text() == "first"
    with staged_dir(str(out)) as tmp:
        _write_result(tmp, "second")
    assert sorted(os.listdir(out)) == sorted([MARKER, "result.json"])
    assert (out / "result.json").read_text() == "second"
    assert sorted(os.listdir(tmp_path)) == ["res"]  # no temporaries left


def test_an_output_folder_from_before_the_marker_is_replaced(tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    for name in ("result.json", "fit.exr", "report.png", "config.toml"):
        (out / name).write_text("old")
    with staged_dir(str(out)) as tmp:
        _write_result(tmp, "new")
    assert (out / "result.json").read_text() == "new"
    assert not (out / "fit.exr").exists()


def test_a_failure_or_interrupt_keeps_the_old_result_and_leaves_no_temporary(tmp_path):
    out = tmp_path / "res"
    with staged_dir(str(out)) as tmp:
        _write_result(tmp, "good")
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with staged_dir(str(out)) as tmp:
                _write_result(tmp, "half")
                raise exc
        assert (out / "result.json").read_text() == "good"
        assert sorted(os.listdir(tmp_path)) == ["res"]


def test_the_old_result_is_never_missing_during_the_swap(tmp_path):
    # A reader polling --out while 40 runs replace it must always find a result.
    out = tmp_path / "res"
    with staged_dir(str(out)) as tmp:
        _write_result(tmp, "0")
    missing = []
    done = threading.Event()

    def watch():
        while not done.is_set():
            try:
                (out / "result.json").read_text()
            except OSError:
                missing.append(1)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        for i in range(40):
            with staged_dir(str(out)) as tmp:
                _write_result(tmp, str(i))
    finally:
        done.set()
        watcher.join()
    assert not missing
    assert (out / "result.json").read_text() == "39"


def test_a_killed_runs_temporary_is_removed_and_a_foreign_one_only_reported(tmp_path):
    pid = _dead_pid()
    ours = tmp_path / f".res.tmp-{pid}-abc"
    ours.mkdir()
    (ours / MARKER).write_text("{}")
    (ours / "fit.exr").write_text("half")
    legacy = tmp_path / ".res.old-xyz"  # no pid, no marker: not provably fitter's
    legacy.mkdir()
    (legacy / "x").mkdir()
    alive = tmp_path / f".res.tmp-{os.getpid()}-def"  # a run still going
    alive.mkdir()
    (alive / MARKER).write_text("{}")
    notes = clean_stale(str(tmp_path), "res")
    assert not ours.exists()
    assert legacy.exists() and alive.exists()
    assert any("removed" in n for n in notes) and any(str(legacy) in n for n in notes)


def test_a_result_moved_aside_by_a_killed_swap_is_restored(tmp_path):
    # Where no atomic exchange exists, the old result waits under .tmp-PID-X.old.
    aside = tmp_path / f".res.tmp-{_dead_pid()}-abc.old"
    aside.mkdir()
    _write_result(aside, "old")
    with staged_dir(str(tmp_path / "res")) as tmp:
        assert (tmp_path / "res" / "result.json").read_text() == "old"
        _write_result(tmp, "new")
    assert (tmp_path / "res" / "result.json").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["res"]


def test_a_broken_link_or_a_file_as_out_is_refused(tmp_path):
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "nowhere")
    with pytest.raises(OutputError, match="broken symbolic link"):
        with staged_dir(str(link)):
            pass
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a folder"):
        with staged_dir(str(tmp_path / "file")):
            pass
    assert (tmp_path / "file").read_text() == "x"


def test_a_link_to_a_fitter_folder_is_written_through(tmp_path):
    real = tmp_path / "scratch" / "res"
    with staged_dir(str(real)) as tmp:
        _write_result(tmp, "a")
    link = tmp_path / "res"
    link.symlink_to(real)
    with staged_dir(str(link)) as tmp:
        _write_result(tmp, "b")
    assert link.is_symlink() and (real / "result.json").read_text() == "b"


def test_a_failure_removes_only_the_folders_it_made(tmp_path):
    # os.removedirs went on up through the user's own empty folders.
    users = tmp_path / "runs"
    users.mkdir()
    out = users / "new" / "deeper" / "res"
    with pytest.raises(RuntimeError):
        with staged_dir(str(out)):
            raise RuntimeError("the job failed")
    assert users.is_dir() and list(users.iterdir()) == []
