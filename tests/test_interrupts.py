"""Real life (issue 20): interruptions, outputs that are inputs, two writers on one output, re-runs over a
checkpoint, and the cache. Signals are sent to real subprocesses running the real command line."""

import functools
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crater_thermal import cache, io
from crater_thermal.errors import ConfigError, OutputLockedError

REPO = Path(__file__).resolve().parents[1]

CASE = """
name = "{name}"
[crater]
kind = "crater"
diameter_km = 2.0
facets = {facets}
[location]
lat_deg = -85.0
[period]
start = "2019-01-01"
end = "{end}"
spinup = "fixed"
spinup_days = 1.0
initial_temperature_K = 100.0
[steps]
flux_step_hours = 4.0
[replay]
profiles = ["1300/1800", "800/1100"]
[output]
checkpoint_interval_steps = 40
"""


def write_case(folder: Path, name="long", facets=150, end="2019-12-31") -> Path:
    path = folder / f"{name}.toml"
    path.write_text(CASE.format(name=name, facets=facets, end=end))
    return path


def env(**extra):
    return dict(os.environ, PYTHONPATH=str(REPO), CRATER_THERMAL_QUIET="1", **extra)


def cli(*args, **extra):
    return subprocess.run(
        [sys.executable, "-m", "crater_thermal", *map(str, args)],
        env=env(**extra),
        capture_output=True,
        text=True,
        timeout=600,
    )


def start(*args):
    return subprocess.Popen(
        [sys.executable, "-m", "crater_thermal", *map(str, args)],
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for(predicate, proc, timeout=300.0):
    """Poll ``predicate()`` until true while ``proc`` runs; fail if the process ended first."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if predicate():
            return
        if proc.poll() is not None:
            pytest.fail(
                f"the process ended (rc {proc.returncode}) before the moment to interrupt it: {proc.stderr.read()}"
            )
        time.sleep(0.01)
    proc.kill()
    pytest.fail("timed out waiting for the moment to interrupt the process")


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert "Traceback" not in stderr
    return lines[0]


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """A short real run (60 facets, January) and its replay, made through the CLI."""
    d = tmp_path_factory.mktemp("small")
    case = write_case(d, name="small", facets=60, end="2019-01-31")
    r = cli("run", case, "-o", d / "run.nc")
    assert r.returncode == 0, r.stderr
    r = cli("replay", d / "run.nc", "--profile", "800/1100", "-o", d / "replay.nc")
    assert r.returncode == 0, r.stderr
    return d


# ----------------------------------------------------------------------------- signals


@pytest.mark.slow
def test_run_interrupted_by_term_and_int_locked_meanwhile_and_rerun_refused(tmp_path):
    """One long run onto an existing output, with --overwrite:
    * a second run to the same output while the first works is refused at once (lock);
    * SIGTERM: exit 143, one line naming --resume, the old output byte for byte, the lock released;
    * a plain re-run refuses (names --resume and --overwrite) and keeps the checkpoint;
    * a --resume interrupted by SIGINT: exit 130, the checkpoint still there.

    Three years of 150 facets (a whole year is ~1.5 s of work): the resumed run is signalled once it has
    written a checkpoint of its own (it is then inside its record), with seconds of work still ahead."""
    case = write_case(tmp_path, end="2021-12-31")
    out = tmp_path / "run.nc"
    out.write_bytes(b"an earlier result the user keeps")
    before = digest(out)
    ckpt = Path(str(out) + ".checkpoint.npz")
    lock = io.lock_path(out)

    first = start("run", case, "-o", out, "--overwrite")
    wait_for(ckpt.exists, first)
    assert lock.exists() and json.loads(lock.read_text())["pid"] == first.pid
    second = cli("run", case, "-o", out, "--overwrite")
    assert second.returncode == 2
    line = one_line(second.stderr)
    assert line.startswith("error: ") and f"process {first.pid}" in line and str(lock) in line
    assert first.poll() is None, "the refused second run must not disturb the first"

    first.send_signal(signal.SIGTERM)
    _, err = first.communicate(timeout=120)
    assert first.returncode == 143, err
    line = one_line(err)
    assert line.startswith("error: interrupted (SIGTERM)") and "--resume" in line and str(ckpt) in line
    assert digest(out) == before  # nothing damaged
    assert ckpt.exists() and not lock.exists()
    assert not any(p.name.endswith(".tmp.nc") for p in tmp_path.iterdir())

    again = cli("run", case, "-o", out)
    assert again.returncode == 2
    line = one_line(again.stderr)
    assert "--resume" in line and "--overwrite" in line and str(ckpt) in line
    assert ckpt.exists() and digest(out) == before

    stamp = ckpt.stat().st_mtime_ns
    resumed = start("run", case, "-o", out, "--resume")
    wait_for(lambda: lock.exists() and json.loads(lock.read_text() or "{}").get("pid") == resumed.pid, resumed)
    wait_for(lambda: ckpt.exists() and ckpt.stat().st_mtime_ns != stamp, resumed)  # into its record
    resumed.send_signal(signal.SIGINT)
    _, err = resumed.communicate(timeout=120)
    assert resumed.returncode == 130, err
    assert one_line(err).startswith("error: interrupted (SIGINT)")
    assert ckpt.exists() and digest(out) == before and not lock.exists()


def test_replay_interrupted_leaves_nothing(small_run, tmp_path):
    out = tmp_path / "grid.nc"
    proc = start("replay", small_run / "run.nc", "--density-grid", "1300:1970:10", "-o", out)
    wait_for(lambda: any(p.name.startswith(".grid.nc.") for p in tmp_path.iterdir()), proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert one_line(err).startswith("error: interrupted (SIGINT); no output was written")
    assert list(tmp_path.iterdir()) == []  # no output, no temporary, no lock


def _drawing_figures(out: Path) -> bool:
    """The report is mid-work: its temporary figures folder holds a first figure."""
    return out.is_dir() and any(
        p.name.startswith(".figures.") and any(p.glob("*.png")) for p in out.iterdir() if p.is_dir()
    )


def test_report_interrupted_leaves_no_empty_folder(small_run, tmp_path):
    """SIGINT while the report draws its figures (several seconds of work are left then): exit 130, one line,
    and the folder it created is gone. The signal is sent only while the process is seen running; should the
    report still have finished first (a loaded machine), the attempt is repeated rather than misread."""
    for attempt in range(3):
        work = tmp_path / f"attempt{attempt}"
        work.mkdir()
        out = work / "report"
        proc = start("report", small_run / "run.nc", small_run / "replay.nc", "-o", out, "--no-snapshots")
        wait_for(functools.partial(_drawing_figures, out), proc)
        if proc.poll() is not None:
            continue
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
        if proc.returncode == 0 and (out / "report.html").exists():
            continue  # it completed between the check and the signal: a finished report, not a swallowed signal
        assert proc.returncode == 130, err
        assert one_line(err).startswith("error: interrupted (SIGINT)")
        assert list(work.iterdir()) == []
        return
    pytest.fail("the report finished before it could be interrupted in three attempts")


# ----------------------------------------------------------------------------- inputs are never outputs


def test_replay_refuses_to_overwrite_its_input(small_run, tmp_path):
    run = small_run / "run.nc"
    before = digest(run)
    for spelling in (
        run,
        small_run / "." / "run.nc",
        small_run.parent / small_run.name / ".." / small_run.name / "run.nc",
    ):
        r = cli("replay", spelling, "--profile", "800/1100", "-o", spelling, "--overwrite")
        assert r.returncode == 2
        assert "is the input" in one_line(r.stderr)
    link = tmp_path / "link.nc"
    link.symlink_to(run)
    r = cli("replay", run, "--profile", "800/1100", "-o", link, "--overwrite")
    assert r.returncode == 2 and "is the input" in one_line(r.stderr)
    hard = tmp_path / "hard.nc"
    os.link(run, hard)  # another name, the same inode
    r = cli("replay", run, "--profile", "800/1100", "-o", hard, "--overwrite")
    assert r.returncode == 2 and "is the input" in one_line(r.stderr)
    assert digest(run) == before


def test_run_refuses_its_case_file_as_output(tmp_path):
    case = write_case(tmp_path, name="c", facets=60, end="2019-01-03")
    before = digest(case)
    r = cli("run", case, "-o", case, "--overwrite")
    assert r.returncode == 2 and "is the input" in one_line(r.stderr)
    assert digest(case) == before


def test_report_refuses_to_replace_an_input(small_run, tmp_path):
    out = tmp_path / "r"
    out.mkdir()
    replay = out / "summary.json"  # the replay stored where the report would write its summary
    replay.write_bytes((small_run / "replay.nc").read_bytes())
    before = digest(replay)
    r = cli("report", small_run / "run.nc", replay, "-o", out, "--overwrite", "--no-snapshots")
    assert r.returncode == 2 and "is the input" in one_line(r.stderr)
    assert digest(replay) == before


def test_refuse_input_as_output_folder_holding_an_input(tmp_path):
    (tmp_path / "figures").mkdir()
    inp = tmp_path / "figures" / "old.nc"
    inp.write_bytes(b"x")
    with pytest.raises(ConfigError, match="holds the input"):
        io.check_output(tmp_path / "figures", overwrite=True, folder=True, inputs=[inp])
    io.check_output(tmp_path / "other.nc", overwrite=True, inputs=[inp, None, tmp_path / "missing.nc"])


# ----------------------------------------------------------------------------- one writer per output


def test_lock_refuses_a_second_process_and_is_released(tmp_path):
    out = tmp_path / "out.nc"
    code = (
        "import sys\nfrom crater_thermal import io\nfrom crater_thermal.errors import OutputLockedError\n"
        f"try:\n    with io.output_lock({str(out)!r}):\n        print('got it')\n"
        "except OutputLockedError as e:\n    print('refused:', e)\n"
    )
    with io.output_lock(out) as lock:
        held = json.loads(lock.read_text())
        assert held["pid"] == os.getpid() and held["host"] == socket.gethostname()
        r = subprocess.run([sys.executable, "-c", code], env=env(), capture_output=True, text=True, timeout=60)
        assert r.stdout.startswith("refused:") and str(os.getpid()) in r.stdout, r.stdout + r.stderr
    assert not lock.exists()
    r = subprocess.run([sys.executable, "-c", code], env=env(), capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "got it", r.stderr


def test_stale_lock_of_a_dead_process_is_taken_over_with_a_warning(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "out.nc"
    lock = io.lock_path(out)
    lock.write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(), "started_utc": "2026-01-01"}))
    with pytest.warns(UserWarning, match="stale lock"):
        with io.output_lock(out):
            assert json.loads(lock.read_text())["pid"] == os.getpid()
    assert not lock.exists()


def test_lock_of_another_host_is_refused_and_kept(tmp_path):
    out = tmp_path / "out.nc"
    lock = io.lock_path(out)
    lock.write_text(json.dumps({"pid": 1, "host": "some-other-node", "started_utc": "2026-01-01"}))
    with pytest.raises(OutputLockedError, match="some-other-node"):
        with io.output_lock(out):
            pass
    assert lock.exists()


def test_lock_survives_an_error_inside(tmp_path):
    out = tmp_path / "out.nc"
    with pytest.raises(RuntimeError):
        with io.output_lock(out):
            raise RuntimeError("boom")
    assert not io.lock_path(out).exists()


# ----------------------------------------------------------------------------- the cache


def test_unwritable_cache_warns_once_and_runs_uncached(tmp_path):
    case = write_case(tmp_path, name="c", facets=60, end="2019-01-03")
    r = cli("run", case, "-o", tmp_path / "run.nc", CRATER_THERMAL_CACHE="/proc/crater_thermal_cache")
    assert r.returncode == 0, r.stderr
    warnings_ = [ln for ln in r.stderr.splitlines() if "cache" in ln]
    assert len(warnings_) == 1 and warnings_[0].startswith("warning: the cache /proc/crater_thermal_cache")
    assert (tmp_path / "run.nc").is_file()


def test_cache_info_and_clear(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    root.mkdir()
    keep = root / "not_ours.txt"  # clear removes only crater_thermal's own sub-folders
    keep.write_text("x")
    case = write_case(tmp_path, name="c", facets=60, end="2019-01-03")
    r = cli("run", case, "-o", tmp_path / "run.nc", CRATER_THERMAL_CACHE=str(root))
    assert r.returncode == 0, r.stderr
    monkeypatch.setenv("CRATER_THERMAL_CACHE", str(root))
    files = [p for p in root.rglob("*.npz")]
    expected = sum(p.stat().st_size for p in files)
    assert files and cache.info()["bytes"] == expected and cache.info()["files"] == len(files)
    r = cli("cache", "info", CRATER_THERMAL_CACHE=str(root))
    assert r.returncode == 0 and str(root) in r.stdout and "viewfactors: 1 files" in r.stdout
    r = cli("cache", "clear", CRATER_THERMAL_CACHE=str(root))
    assert r.returncode == 0 and f"removed {len(files)} files" in r.stdout
    assert cache.info()["files"] == 0 and keep.read_text() == "x"
    r = cli("cache", "clear", "--kind", "nonsense", CRATER_THERMAL_CACHE=str(root))
    assert r.returncode == 2 and "viewfactors, horizons" in one_line(r.stderr)


def test_steady_and_mesh_dem_refuse_their_input_as_output(tmp_path):
    mesh = tmp_path / "crater.ply"
    assert cli("mesh", "crater", "--diameter-km", "1", "--facets", "60", "-o", mesh).returncode == 0
    before = digest(mesh)
    r = cli("steady", mesh, "--sun-elevation-deg", "10", "-o", mesh, "--overwrite")
    assert r.returncode == 2 and "is the input" in one_line(r.stderr) and digest(mesh) == before
    dem = tmp_path / "site.tif"
    r = cli("dem", "synth", "--lat-deg", "-87", "--size-km", "4", "--pixel-m", "100", "-o", dem)
    assert r.returncode == 0, r.stderr
    before = digest(dem)
    r = cli(
        "mesh", "dem", dem, "--center-lat", "-87", "--center-lon", "0", "--radius-km", "1", "-o", dem, "--overwrite"
    )
    assert r.returncode == 2 and "is the input" in one_line(r.stderr) and digest(dem) == before


def test_swallowed_interrupt_still_prevents_the_commit(tmp_path, monkeypatch):
    """A signal whose exception some C code swallowed (the process ran on) must still stop the output's final
    rename: the earlier output stays byte for byte and no temporary is left."""
    from crater_thermal import errors

    out = tmp_path / "result.txt"
    out.write_text("the earlier result")
    monkeypatch.setattr(errors, "_RECEIVED_SIGNALS", [])
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # note_interrupt replaces it
    with pytest.raises(errors.Interrupted) as info:
        with io.atomic_output(out, overwrite=True) as tmp:
            tmp.write_text("a new result")
            errors.note_interrupt(signal.SIGINT)  # what the CLI's handler records before its raise is lost
    assert info.value.exit_code == 130
    assert out.read_text() == "the earlier result"
    assert [p.name for p in tmp_path.iterdir()] == ["result.txt"]


def test_a_signal_after_the_output_is_in_place_says_it_was_written(tmp_path, monkeypatch, capsys):
    """A signal that arrives once the run's output was renamed into place (only the checkpoint's and the
    scratch store's removal left, or the lock's release) exits 130 but does not claim that nothing was
    written: the line names the output, which is complete. A run's work is simulated by a stand-in that
    replaces the output (as the real writers do, by renaming a finished temporary) and is then interrupted."""
    from crater_thermal import api, cli
    from crater_thermal.errors import Interrupted

    case = write_case(tmp_path, name="c", facets=60, end="2019-01-03")
    out = tmp_path / "run.nc"
    out.write_bytes(b"an earlier result")

    def finished_then_interrupted(case_path, output, **kw):
        tmp = Path(str(output) + ".tmp")
        tmp.write_bytes(b"the new, complete result")
        os.replace(tmp, output)
        raise Interrupted(signal.SIGINT)

    monkeypatch.setattr(cli, "_install_signal_handlers", lambda: None)  # keep pytest's own handlers
    monkeypatch.setattr(cli, "_WATCHED", [])
    monkeypatch.setattr(api, "run", finished_then_interrupted)
    with pytest.raises(SystemExit) as ended:
        cli.main(["run", str(case), "-o", str(out), "--overwrite"])
    assert ended.value.code == 130
    line = one_line(capsys.readouterr().err)
    assert line.startswith("error: interrupted (SIGINT)") and f"{out} had been written in full" in line
    assert "no output was written" not in line

    # the same interruption before anything was renamed keeps the usual line
    def interrupted(case_path, output, **kw):
        raise Interrupted(signal.SIGINT)

    monkeypatch.setattr(cli, "_WATCHED", [])
    monkeypatch.setattr(api, "run", interrupted)
    with pytest.raises(SystemExit) as ended:
        cli.main(["run", str(case), "-o", str(out), "--overwrite"])
    assert ended.value.code == 130
    assert one_line(capsys.readouterr().err).endswith("no output was written or changed")


HALF_BUILT = """
import os, signal, sys
from crater_thermal import cli

class HalfBuilt:  # like llvmlite's OutputString: its destructor needs what the constructor sets last
    def __init__(self):
        os.kill(os.getpid(), signal.SIGINT)  # the signal lands here, before _ptr is set
        self._ptr = None

    def __del__(self):
        if self._ptr is not None:
            pass

def app(args, standalone_mode):
    keep = [HalfBuilt()]  # never reached
    return keep

cli.app = app
cli.main(["run"])
"""


def test_interrupt_inside_a_constructor_still_prints_one_line():
    """CI once saw the SIGINT land in llvmlite's ``OutputString.__init__`` while numba compiled: the freed,
    half-built object's destructor then printed a traceback after the one-line message (this test printed
    the same before ``errors.note_interrupt`` dropped such failures). The real handler is installed by
    ``cli.main`` in a real subprocess, and the signal is sent inside such a constructor."""
    r = subprocess.run([sys.executable, "-c", HALF_BUILT], env=env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 130, r.stderr
    assert one_line(r.stderr) == "error: interrupted (SIGINT); no output was written or changed"
