"""A replay the disk cannot hold: the replay dataset's size (profiles x samples x facets x 4 bytes before
compression) and a distributed replay's chunk files (the same, uncompressed, kept for ``--resume``) are
checked against the output disk's free space before any column is solved. The sizes here are counted
from the run file's dimensions, not taken from the code under test."""

from __future__ import annotations

import shutil
import warnings
from collections import namedtuple

import pytest

from crater_thermal import cli, cluster, io, runner
from crater_thermal.errors import DiskSpaceError

from synthetic import make_run

Usage = namedtuple("Usage", "total used free")
GRID = "1300:1900:300"  # 6 profiles
N_PROFILES = 6


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("replay_disk")
    make_run(lat_deg=-86.0, n_lunar_days=1.0, n_rings=4).isel(facet=slice(0, 64)).to_netcdf(d / "run.nc")
    with io.open_run(d / "run.nc") as ds:
        nbytes = N_PROFILES * ds.sizes["time"] * ds.sizes["facet"] * 4  # float32 temperatures
    return d / "run.nc", nbytes


def _free(monkeypatch, n: int) -> None:
    monkeypatch.setattr(shutil, "disk_usage", lambda p: Usage(10**13, 0, int(n)))


def test_local_replay_warns_when_the_replay_may_not_fit(run_file, tmp_path, monkeypatch):
    """One byte short of the uncompressed size: a warning naming the size, and the replay written
    (compressed, it fits); with room for it: no warning."""
    flux, nbytes = run_file
    _free(monkeypatch, nbytes - 1)
    with pytest.warns(UserWarning, match="may not fit") as rec:
        runner.replay_file(flux, [], density_grid=GRID, output=tmp_path / "a.nc", progress=False)
    assert "6 profiles" in str(rec[0].message) and "an existing output is kept" in str(rec[0].message)
    with io.open_replay(tmp_path / "a.nc") as ds:
        assert ds.sizes["profile"] == N_PROFILES
    _free(monkeypatch, nbytes)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        runner.replay_file(flux, [], density_grid=GRID, output=tmp_path / "b.nc", progress=False)


def test_distributed_replay_whose_chunks_cannot_fit_is_refused_before_any_work(run_file, tmp_path, monkeypatch):
    """Less free space than the chunks: a one-line DiskSpaceError before the cluster is asked for, no chunk
    folder left, an existing output kept. Exactly the chunks' size free: past the check (the cluster is
    asked for), with a warning that the assembled replay may not fit beside them."""
    flux, nbytes = run_file
    out = tmp_path / "kept.nc"
    out.write_bytes(b"an earlier result")

    class Asked(Exception):
        pass

    def no_cluster(*a, **k):
        raise Asked

    monkeypatch.setattr(cluster, "connect", no_cluster)
    _free(monkeypatch, nbytes - 1)
    with pytest.raises(DiskSpaceError) as err:
        cluster.replay_file(flux, [], density_grid=GRID, output=out, workers=1, overwrite=True, progress=False)
    msg = str(err.value)
    assert "\n" not in msg and "GB free" in msg and "-o" in msg and "6 profiles" in msg, msg
    assert out.read_bytes() == b"an earlier result" and not cluster.chunk_folder(out).exists()
    _free(monkeypatch, nbytes)
    with pytest.warns(UserWarning, match="finished chunks are kept for --resume"), pytest.raises(Asked):
        cluster.replay_file(flux, [], density_grid=GRID, output=out, workers=1, overwrite=True, progress=False)
    assert out.read_bytes() == b"an earlier result"


def test_cli_refuses_a_distributed_replay_the_disk_cannot_hold(run_file, tmp_path, monkeypatch, capsys):
    """The command line: one line on stderr, exit code 2, no traceback, nothing written."""
    flux, nbytes = run_file
    _free(monkeypatch, nbytes // 3)
    with pytest.raises(SystemExit) as exc:
        cli.main(["replay", str(flux), "--density-grid", GRID, "--workers", "1", "-o", str(tmp_path / "r.nc")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: this replay's chunks need ~") and "\n" not in err and "Traceback" not in err, err
    assert not (tmp_path / "r.nc").exists()
