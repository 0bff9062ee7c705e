"""A batch that never lies: SIGKILL at several points and an immediate restart give the outputs of an
uninterrupted batch; no worker outlives the batch; one writer per output folder; a real Dask
scheduler and worker in other processes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from pipeline.app.batch import ATTEMPT, run_batch
from pipeline.app.manifest import MANIFEST, verify_manifest
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from tests.conftest import REPO
from tests.helpers import untimed

SAMPLE = REPO / "data" / "clips" / "sample_small"
METHODS = "triangulation,ekf"


def make_input(root: Path, n: int = 3, corrupt: bool = False) -> Path:
    for i in range(n):
        shutil.copytree(SAMPLE, root / f"clip{i}")
    if corrupt:
        shutil.copytree(SAMPLE, root / "corrupt")
        (root / "corrupt" / "right.mp4").write_bytes(b"\x00" * 5000)
    return root


def batch_cmd(inp: Path, out: Path, *extra: str) -> list[str]:
    """The batch these tests kill and restart (recordings without frames: images are not what
    they test, and encoding them would only make the kill windows slower)."""
    return [sys.executable, "-m", "pipeline.app.cli", "batch", str(inp), "-o", str(out), "--workers", "2",
            "--methods", METHODS, "--no-images", *extra]


def clip_outputs(folder: Path) -> dict[str, object]:
    """A clip's outputs, comparable across runs: CSVs byte for byte, metrics without timings,
    and the set of files (the recording and the report carry timings and run ids)."""
    out: dict[str, object] = {"files": sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()
                                              and not p.name.startswith("."))}
    for p in sorted(folder.rglob("*.csv")):
        out[str(p.relative_to(folder))] = p.read_bytes()
    metrics = json.loads((folder / "metrics.json").read_text())
    metrics["checks"] = [{k: v for k, v in c.items() if k != "message"} for c in metrics.get("checks", [])]
    out["metrics"] = untimed(metrics)
    return out


def _running(p: psutil.Process) -> bool:
    try:
        return p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, Path]:
    """An uninterrupted batch, during which a second batch on the same output is refused."""
    root = tmp_path_factory.mktemp("ref")
    inp, out = make_input(root / "in"), root / "out"
    first = subprocess.Popen(batch_cmd(inp, out), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lock = out / ".stereotrack.lock"
    deadline = time.time() + 60
    while time.time() < deadline and not (lock.is_file() and lock.stat().st_size > 0):
        time.sleep(0.05)
    second = subprocess.run(batch_cmd(inp, out), capture_output=True, text=True, timeout=120)
    first_err = first.communicate(timeout=300)[1]
    assert first.returncode == 0, first_err
    assert second.returncode == 2, second.stderr
    assert f"PID {first.pid}" in second.stderr and "in use" in second.stderr
    assert "Traceback" not in second.stderr
    return inp, out


@pytest.mark.slow
def test_second_batch_is_refused_and_first_completes(reference):
    _inp, out = reference
    for i in range(3):
        assert verify_manifest(out / f"clip{i}") is None
        m = json.loads((out / f"clip{i}" / "metrics.json").read_text())
        assert m["methods"]["ekf"]["rmse"] < 0.05
        # the report's replay command names the clip's folder, not the attempt's hidden one (#41)
        assert f"stereotrack view {out / f'clip{i}'}`" in (out / f"clip{i}" / "report.md").read_text()
    assert {c for c in read_csv(out / "summary.csv")["clip"]} == {"clip0", "clip1", "clip2"}
    assert not (out / ".stereotrack.lock").exists()  # released cleanly


def _kill_point(out: Path, point: str) -> bool:
    """Whether the batch writing ``out`` has reached ``point``."""
    names = [p.name for p in out.iterdir()] if out.is_dir() else []
    committed = len([n for n in names if n.startswith("clip")])
    return {"start-up": True,
            "lock taken": (out / ".stereotrack.lock").is_file() and (out / ".stereotrack.lock").stat().st_size > 0,
            "clips in progress": any(".partial-" in n for n in names),
            "first commit": committed >= 1,
            "second commit": committed >= 2}[point]


@pytest.mark.slow
def test_killed_at_five_points_then_restarted(reference, tmp_path):
    """SIGKILL to the batch's main process only, at five points (start-up, lock taken, clips in
    progress, after the first and after the second commit), each followed at once by a restart:
    no process of a killed batch is alive 2 s later, nothing unverified is ever presented as a
    clip, and the last restart exits 0 with the outputs of the uninterrupted batch."""
    _, ref_out = reference
    inp = make_input(tmp_path / "in")
    out = tmp_path / "out"
    for point in ("start-up", "lock taken", "clips in progress", "first commit", "second commit"):
        proc = subprocess.Popen(batch_cmd(inp, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.time() + 60
        while time.time() < deadline and proc.poll() is None and not _kill_point(out, point):
            time.sleep(0.02)
        assert proc.poll() is None, f"the batch ended before '{point}'"
        family = descendants(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        _gone, alive = psutil.wait_procs(family, timeout=2.0)
        alive = [p for p in alive if _running(p)]  # a zombie has ended; only its reaping is pending
        assert not alive, f"after a kill at '{point}': {[p.pid for p in alive]} still alive"
        for d in out.glob("clip*"):  # whatever is presented as a clip verifies
            assert (d / MANIFEST).is_file() and verify_manifest(d) is None, d
    done = subprocess.run(batch_cmd(inp, out), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    for i in range(3):
        assert clip_outputs(out / f"clip{i}") == clip_outputs(ref_out / f"clip{i}"), i


@pytest.mark.slow
def test_corrupted_output_is_redone(reference, tmp_path):
    """A clip folder whose files no longer match their manifest (or that has none) is redone."""
    _, ref_out = reference
    inp = tmp_path / "in"
    shutil.copytree(reference[0], inp)
    out = tmp_path / "out"
    shutil.copytree(ref_out, out)
    (out / "clip0" / "estimates" / "ekf.csv").write_text("frame\n")
    (out / "clip1" / MANIFEST).unlink()
    settings = RunSettings(methods=METHODS.split(","), images=False, figures=False)
    outcomes = {o.clip: o.status for o in run_batch(inp, out, settings, workers=1)}
    assert outcomes == {"clip0": "ok", "clip1": "ok", "clip2": "skipped"}
    for i in range(3):
        assert clip_outputs(out / f"clip{i}") == clip_outputs(ref_out / f"clip{i}")
    # outputs made with other settings than the ones asked for now do not count as done
    asked = {"detector": "blob", "methods": ["triangulation"], "markers": None, "root_markers": None, "calib_units": None,
             "configs": None, "images": False, "time_offset": "auto"}
    assert verify_manifest(out / "clip2", asked) == "made with other settings (methods)"
    assert verify_manifest(out / "clip2", {**asked, "methods": METHODS.split(",")}) is None


def test_run_is_locked_and_cleans_leftovers(tmp_path, monkeypatch, capsys):
    from pipeline.core.lifeline import OutputLock
    from tests.helpers import cli

    clip = tmp_path / "clip"
    shutil.copytree(SAMPLE, clip)
    (clip / "out" / "estimates").mkdir(parents=True)
    leftover = clip / "out" / "estimates" / ".ekf.partial-abc123.csv"
    leftover.write_text("half")
    with OutputLock(clip / "out", "test holder"):
        rc, _, err = cli(monkeypatch, capsys, "run", clip, "--methods", "triangulation")
    assert rc == 2 and "in use by test holder" in err and f"PID {os.getpid()}" in err
    assert leftover.exists()
    rc, _, err = cli(monkeypatch, capsys, "run", clip, "--methods", "triangulation")
    assert rc == 0, err
    assert not leftover.exists() and (clip / "out" / "report.md").is_file()


def test_stale_lock_is_taken_over_with_a_warning(tmp_path):
    from pipeline.core.lifeline import LOCK_NAME, OutputLock

    tmp_path.joinpath(LOCK_NAME).write_text(json.dumps({"pid": 999999, "host": "elsewhere", "command": "old batch"}))
    with pytest.warns(UserWarning, match="taking over the lock of PID 999999"), OutputLock(tmp_path, "new"):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()


def _dask_cluster(tmp_path: Path) -> tuple[Path, list[subprocess.Popen]]:
    """`dask scheduler` and one `dask worker` (with its nanny) in processes of their own on 127.0.0.1."""
    sched_file = tmp_path / "scheduler.json"
    common = ["--no-dashboard"]
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--scheduler-file", str(sched_file), *common],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)]
    deadline = time.time() + 60
    while time.time() < deadline and not sched_file.is_file():
        time.sleep(0.1)
    procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", "--scheduler-file", str(sched_file),
                                   "--nthreads", "1", "--nworkers", "1", *common],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO))
    return sched_file, procs


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in reversed(procs):
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()


@pytest.mark.slow
def test_dask_worker_killed_mid_batch(reference, tmp_path):
    """SIGKILL to the Dask worker process (not its nanny) while it holds a clip: Dask runs the clip
    again on the restarted worker; the summary records two attempts and the dead worker, every clip
    equals the local pool's, and the dead attempt's temporary folder is gone at the end."""
    _, ref_out = reference
    inp = make_input(tmp_path / "in")
    sched_file, procs = _dask_cluster(tmp_path)
    try:
        out = tmp_path / "out"
        batch = subprocess.Popen(batch_cmd(inp, out, "--scheduler-file", str(sched_file)), stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, cwd=REPO)
        deadline = time.time() + 120
        # the attempt is the worker's once its record is in its folder (killed between the folder and the
        # record, as a loaded machine once did, the attempt leaves nothing to count)
        while time.time() < deadline and not (out.is_dir() and any(".partial-" in p.name and (p / ATTEMPT).is_file()
                                                                   for p in out.iterdir())):
            time.sleep(0.02)
        holder = next(p for p in out.iterdir() if ".partial-" in p.name).name[1:].split(".partial-")[0]
        (worker,) = [p for p in psutil.Process(procs[1].pid).children(recursive=True)
                     if "spawn_main" in " ".join(p.cmdline())]  # the worker, not the resource tracker
        worker.kill()
        _, err = batch.communicate(timeout=300)
        assert batch.returncode == 0, err
        summary = read_csv(out / "summary.csv")
        attempts = dict(zip(summary["clip"], summary["attempts"], strict=True))
        assert attempts[holder] == 2 and all(a == 1 for c, a in attempts.items() if c != holder), attempts
        assert "the worker running an attempt at it (tcp://127.0.0.1:" in (out / "summary.md").read_text()
        assert not [p for p in out.iterdir() if p.name.startswith(".")]
        for i in range(3):
            assert clip_outputs(out / f"clip{i}") == clip_outputs(ref_out / f"clip{i}"), i
    finally:
        _stop(procs)


@pytest.mark.slow
def test_batch_on_a_real_dask_scheduler_and_worker(reference, tmp_path):
    """`dask scheduler` and `dask worker` in processes of their own on 127.0.0.1; one corrupt clip
    among good ones. The good clips' outputs equal the local pool's; the corrupt one fails alone."""
    _, ref_out = reference
    inp = make_input(tmp_path / "in", corrupt=True)
    sched_file, procs = _dask_cluster(tmp_path)
    try:
        out = tmp_path / "out"
        res = subprocess.run(batch_cmd(inp, out, "--scheduler-file", str(sched_file)), capture_output=True, text=True,
                             timeout=300, cwd=REPO)
        assert res.returncode == 1, res.stderr  # the corrupt clip failed, the batch went on
        summary = read_csv(out / "summary.csv")
        status = dict(zip(summary["clip"], summary["status"], strict=True))
        assert status == {"clip0": "ok", "clip1": "ok", "clip2": "ok", "corrupt": "failed"}
        err = next(e for c, e in zip(summary["clip"], summary["error"], strict=True) if c == "corrupt")
        assert "right.mp4" in err
        for i in range(3):
            assert clip_outputs(out / f"clip{i}") == clip_outputs(ref_out / f"clip{i}"), i
    finally:
        _stop(procs)


def test_child_processes_start_with_one_blas_thread(monkeypatch):
    """Workers and render processes start with one BLAS/OpenMP thread unless the user chose a
    number; this process's own environment is left as it was."""
    import subprocess
    import sys

    from pipeline.core.lifeline import child_environment

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    code = "import os; print(os.environ['OMP_NUM_THREADS'], os.environ['MKL_NUM_THREADS'], os.environ['LP_NUM_THREADS'])"
    with child_environment({"LP_NUM_THREADS": "1"}):
        seen = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert seen == ["1", "3", "1"]
    assert "OMP_NUM_THREADS" not in os.environ and "LP_NUM_THREADS" not in os.environ
    assert os.environ["MKL_NUM_THREADS"] == "3"
