"""``fitter batch`` / ``fitter.batch.run_batch`` on Dask: results, faults, resume.

Tiny jobs (24x24, 2x2 supersampling, forward-model targets) on small clusters
bound to 127.0.0.1: an embedded LocalCluster, an external ``dask scheduler``
with two ``dask worker`` processes, a worker killed while it fits.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import fitter
from fitter import cli, imageio
from fitter.batch import BatchError, expand_configs, run_batch
from fitter.batch._table import read_csv
from fitter.config import dumps_toml, load_config
from fitter.outdir import MARKER
from small_case import SMALL

distributed = pytest.importorskip("distributed")


def _tiny(m: float) -> dict:
    d = copy.deepcopy(SMALL)
    d["scene"]["width"] = d["scene"]["height"] = 24
    d["material"]["truth"]["torrance_sparrow.m"] = m
    return d


def _write(folder, name: str, data: dict) -> str:
    """A config ``folder/name.toml`` and its forward-model target ``folder/name.exr``."""
    os.makedirs(folder, exist_ok=True)
    data = copy.deepcopy(data)
    data["fit"]["target"] = f"{name}.exr"
    path = os.path.join(folder, f"{name}.toml")
    with open(path, "w") as fh:
        fh.write(dumps_toml(data))
    job = load_config(path)
    img = np.asarray(fitter.render(job.material.full_params({**job.fixed, **job.truth}),
                                   job.scene, job.material))
    imageio.write_image(os.path.join(folder, f"{name}.exr"), img)
    return path


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch_cases")
    paths = [_write(root, f"case{i}", _tiny(m)) for i, m in enumerate([0.15, 0.25])]
    bad = root / "bad.toml"
    bad.write_text("[scene]\nwidth = -1\n")
    return paths, str(bad)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _temporaries(folder) -> list[str]:
    return [n for n in os.listdir(folder) if ".tmp-" in n]


def test_configs_from_folders_and_globs_and_shared_stems_get_their_own_folders(tmp_path):
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "x.toml").write_text("")
    (tmp_path / "a" / "y.toml").write_text("")
    found = expand_configs([str(tmp_path / "a"), str(tmp_path / "*" / "x.toml")])
    assert [os.path.relpath(p, tmp_path) for p in found] == ["a/x.toml", "a/y.toml", "b/x.toml"]
    with pytest.raises(BatchError, match="no config matches"):
        expand_configs([str(tmp_path / "nothing*.toml")])
    from fitter.batch._jobs import make_entries

    names = [e.name for e in make_entries(found, None)]  # all three fail to load: still named
    assert names[1] == "y" and names[0] != names[2] and all(n.startswith("x-") for n in
                                                           (names[0], names[2]))


def test_batch_on_a_local_cluster_writes_fit_folders_summary_and_a_bad_config_row(
        cases, tmp_path, capsys):
    paths, bad = cases
    out = tmp_path / "batch"
    rc = cli.main(["batch", *paths, bad, "--out", str(out), "--workers", "2", "--quiet"])
    assert rc == 3  # the bad config: not every job converged
    rows = read_csv(out / "summary.csv")
    assert [r["config"] for r in rows] == [*paths, bad]
    assert [r["status"] for r in rows] == ["converged", "converged", "error"]
    assert "scene.width" in rows[2]["error"] and bad in rows[2]["error"]
    for r, m in zip(rows[:2], [0.15, 0.25]):
        assert abs(float(r["torrance_sparrow.m"]) - m) < 1e-6
        assert float(r["stderr:torrance_sparrow.m"]) >= 0 and r["psnr_db"] == ""
        assert float(r["truth:torrance_sparrow.m"]) == m and float(r["image_rmse"]) < 1e-6
        folder = out / r["out"]
        assert {"result.json", "fit.exr", "residual.exr", "report.png", "config.toml",
                MARKER} <= set(os.listdir(folder))
    assert (out / "summary.png").stat().st_size > 0 and not _temporaries(out)

    # the same numbers as one `fitter fit` of that config
    single = tmp_path / "single"
    assert cli.main(["fit", paths[0], "--out", str(single), "--no-validate", "--quiet"]) == 0
    one = json.loads((single / "result.json").read_text())
    two = json.loads((out / rows[0]["out"] / "result.json").read_text())
    for key, value in one["params"].items():
        if not isinstance(value, str):
            np.testing.assert_allclose(two["params"][key], value, rtol=1e-6)


def test_resume_skips_finished_jobs_and_reruns_a_changed_config(tmp_path):
    a = _write(tmp_path / "cfg", "a", _tiny(0.2))
    b = _write(tmp_path / "cfg", "b", _tiny(0.3))
    out = str(tmp_path / "batch")
    first = run_batch([a, b], out, workers=1)
    assert [r["status"] for r in first] == ["converged"] * 2
    assert not any(r["resumed"] for r in first)
    t0 = time.perf_counter()
    again = run_batch([a, b], out, workers=1)  # nothing to fit: no cluster is started
    assert time.perf_counter() - t0 < 5
    assert [r["resumed"] for r in again] == [True, True]
    assert again[0]["torrance_sparrow.m"] == first[0]["torrance_sparrow.m"]
    data = _tiny(0.3)
    data["material"]["init"]["torrance_sparrow.m"] = 0.35  # b changes: fitted again
    data["fit"]["target"] = "b.exr"
    with open(b, "w") as fh:
        fh.write(dumps_toml(data))
    third = run_batch([a, b], out, workers=1)
    assert [r["resumed"] for r in third] == [True, False]
    assert [r["status"] for r in third] == ["converged"] * 2


def test_unreachable_scheduler_is_exit_2_in_a_few_seconds(cases, tmp_path, capsys):
    paths, _ = cases
    t0 = time.perf_counter()
    rc = cli.main(["batch", paths[0], "--out", str(tmp_path / "o"),
                   "--scheduler", f"tcp://127.0.0.1:{_free_port()}"])
    assert rc == 2 and time.perf_counter() - t0 < 10
    err = capsys.readouterr().err.strip()
    assert err.startswith("fitter: error: --scheduler tcp://127.0.0.1:") and "\n" not in err
    assert not (tmp_path / "o" / "case0").exists()


def test_batch_on_an_external_dask_scheduler_and_two_dask_workers(cases, tmp_path):
    paths, _ = cases
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    dask = [sys.executable, "-m", "dask"]
    procs = [subprocess.Popen([*dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 30
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        for _ in range(2):
            procs.append(subprocess.Popen(
                [*dask, "worker", address, "--nthreads", "1", "--host", "127.0.0.1",
                 "--no-dashboard"], env=env, stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL))
        rows = run_batch(paths, str(tmp_path / "batch"), scheduler=address)
        assert [r["status"] for r in rows] == ["converged"] * 2
        assert all((tmp_path / "batch" / r["out"] / "result.json").exists() for r in rows)
        # the API's other inputs: a Job, and (target array, scene, material), nothing written
        job = load_config(paths[1])
        target = imageio.read_image(job.fit.target)
        rows = run_batch([job, (target, job.scene, job.material)], scheduler=address)
        assert [r["error"] for r in rows] == ["", ""]
        assert rows[0]["out"] == rows[1]["out"] == ""  # no folders without out
        np.testing.assert_allclose(rows[1]["torrance_sparrow.m"], 0.25, rtol=1e-5)
    finally:
        for p in reversed(procs):  # workers first, then the scheduler
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_a_worker_killed_mid_job_has_its_job_run_again_elsewhere(cases, tmp_path,
                                                                 monkeypatch):
    paths, _ = cases
    monkeypatch.setenv("FITTER_CACHE_DIR", "")  # compile in the job: a slow first fit
    out = tmp_path / "batch"
    out.mkdir()
    killed: list[int] = []

    def kill_the_first_writer():  # a staged folder is named .NAME.tmp-<worker pid>-...
        deadline = time.monotonic() + 120
        while not killed and time.monotonic() < deadline:
            for name in _temporaries(out):
                pid = int(name.split(".tmp-")[1].split("-")[0])
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
            time.sleep(0.02)

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None, silence_logs=50) as cluster:
        killer = threading.Thread(target=kill_the_first_writer, daemon=True)
        killer.start()
        rows = run_batch(paths[:1], str(out), scheduler=cluster.scheduler_address)
        killer.join(5)
    assert killed, "no job folder was being written"
    assert rows[0]["status"] == "converged", rows[0]["error"]
    assert (out / rows[0]["out"] / "result.json").exists()
    assert not _temporaries(out)  # the dead worker's staged folder was removed


def test_batch_help_and_command_line_errors_answer_without_dask(tmp_path):
    code = ("import sys\nfrom fitter.cli import main\n"
            f"rc = [main(['batch', '--help']), main(['batch', 'x.toml', '--out', "
            f"{str(tmp_path / 'o')!r}, '--workers', '0']), main(['batch', "
            f"{str(tmp_path / 'none*.toml')!r}, '--out', {str(tmp_path / 'o')!r}])]\n"
            "print(rc, 'distributed' in sys.modules, 'jax' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    # --help 0; --workers 0 and a glob matching nothing: 2, one line each
    assert proc.stdout.splitlines()[-1] == "[0, 2, 2] False False", proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("fitter: error:")]
    assert len(errors) == 2 and "--workers 0" in errors[0] and "no config matches" in errors[1]


def _entries(gigabytes):
    from fitter.batch._jobs import Entry

    return [Entry(i, f"job{i}.toml", memory=g * 1e9) for i, g in enumerate(gigabytes)]


def test_the_embedded_cluster_runs_only_as_many_jobs_side_by_side_as_memory_holds(
        monkeypatch):
    # Dask's default worker limit is the machine's memory over its cores: on 16 cores and
    # 32 GB a 256^2 env-lit fit (4.5 GB estimated by fitter.limits) was stopped on every
    # worker it tried. 25.6 GB usable (80 % of 32) holds 5 such jobs: 5 workers of 5.1 GB.
    from distributed.worker_memory import parse_memory_limit

    from fitter import limits
    from fitter.batch._engine import _local_size

    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    monkeypatch.setattr(limits, "available_bytes", lambda: 32e9)
    dask_auto = parse_memory_limit("auto", 1, logger=logging.getLogger("test"))
    n, limit = _local_size(None, _entries([4.5] * 8 + [1.0]))
    assert n == 5 and limit == max(int(25.6e9 / 5), dask_auto)
    assert limit >= 4.5e9  # every job's estimate fits its worker
    assert _local_size(None, _entries([1.0] * 3))[0] == 3  # small jobs: one per job
    assert _local_size(3, _entries([4.5] * 8))[0] == 3
    with pytest.raises(BatchError, match=r"--workers 8: 8 jobs side by side need about 36\.0 "
                                         r"GB .* use --workers 5 or fewer"):
        _local_size(8, _entries([4.5] * 8))
    n, limit = _local_size(None, _entries([30.0]))  # over the share: one at a time
    assert n == 1 and limit == max(int(25.6e9), dask_auto)


def test_a_job_no_worker_of_an_existing_cluster_can_hold_is_an_error_row(cases, tmp_path):
    # An external cluster's workers keep their own memory limits: a job estimated over
    # the largest is refused before it runs (Dask would stop it on each worker it tried).
    paths, _ = cases
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None, silence_logs=50,
                                  memory_limit="300 MB") as cluster:
        rows = run_batch(paths[:1], str(tmp_path / "batch"),
                         scheduler=cluster.scheduler_address)
    from fitter.limits import scene_bytes

    job = load_config(paths[0])
    need = scene_bytes("fit", job.scene, job.material)  # the model's estimate
    assert rows[0]["status"] == "error" and need > 0.3e9
    assert (f"needs about {need / 1e9:.1f} GB" in rows[0]["error"] and "memory limit of 0.3 GB"
            in rows[0]["error"] and paths[0] in rows[0]["error"]), rows[0]["error"]
    assert not (tmp_path / "batch" / "case0").exists()


def test_the_embedded_cluster_workers_do_not_pause_at_their_memory_limit():
    # A worker keeps most of a fit's peak RSS after it (the allocator): with Dask's
    # pause at 80 % of its limit it could stop taking jobs for good.
    from fitter.batch._engine import _client

    with _client(None, 1, _entries([0.1])) as client:
        assert list(client.run(lambda: __import__("dask").config.get(
            "distributed.worker.memory.pause")).values()) == [False]


def test_progress_line_counts_jobs_in_the_summary_words():
    """The live progress line counts each job under its summary.csv status (a fit
    that failed is "failed", a job that could not run "error"), as the final
    summary line does; before, a failed fit showed as "not converged" and an
    error as "failed"."""
    from fitter.batch._engine import COLOURS, _Progress
    from fitter.batch._task import STATUSES

    assert set(COLOURS) == set(STATUSES)
    with _Progress(True, 4) as bar:
        bar.update({"converged": 2, "max_steps": 0, "failed": 1, "error": 1}, 0)
        text = bar.bar.tasks[0].fields["counts"]
    assert "2 converged" in text and "1 failed" in text and "1 error" in text, text
    assert "max_steps" not in text and "not converged" not in text


def test_run_batch_at_a_scripts_top_level_says_to_guard_it(tmp_path):
    """A script calling run_batch at its top level (the README's example without the
    main guard): the embedded cluster's worker processes import it again, and Dask
    said only "Nanny failed to start"; now a BatchError names the script and the
    guard."""
    script = tmp_path / "batch_script.py"
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    config = os.path.join(root, "configs", "lambert.toml")
    script.write_text("from fitter.batch import run_batch\n"
                      f"run_batch([{config!r}], workers=1, validate=False)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("fitter.batch._jobs.BatchError: the embedded Dask cluster's"), last
    assert str(script) in last and 'if __name__ == "__main__":' in last
