"""Bounded-memory runs and replays (issue 13): block store, streamed run.nc, replay in blocks."""

import json
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crater_thermal import config, io, runner, simulate

CASE = """
name = "{name}"
[crater]
kind = "crater"
diameter_km = 2.0
facets = {facets}
[location]
lat_deg = -85.0
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "{end}"
spinup = "fixed"
spinup_days = 2.0
initial_temperature_K = 100.0
[steps]
flux_step_hours = 4.0
[surface]
albedo = 0.12
emissivity = 0.98
[sun]
point_sun = true
[output]
chunk_mb = {chunk_mb}
checkpoint_interval_steps = {every}
"""


def _case(tmp_path, name, facets=60, end="2019-01-15", chunk_mb=256.0, every=0):
    path = tmp_path / f"{name}.toml"
    path.write_text(CASE.format(name=name, facets=facets, end=end, chunk_mb=chunk_mb, every=every))
    return config.load_case(path)


def test_segment_store_rows_across_blocks(tmp_path):
    store = io.SegmentStore(tmp_path / "s", block=4)
    data = np.arange(11 * 3, dtype=float).reshape(11, 3)
    store.write_rows("x", 0, data[:1])  # a partial first block, then rows that start inside it
    store.write_rows("x", 1, data[1:6])
    store.write_rows("x", 6, data[6:])
    np.testing.assert_array_equal(store.read("x", 0, 11), data)
    np.testing.assert_array_equal(store.read("x", 3, 9), data[3:9])
    with pytest.raises(io.FluxFileError):
        store.read("x", 10, 13)  # past what was written
    with pytest.raises(ValueError):
        store.write("x", 1, data[:2])  # blocks start at multiples of the block size
    store.remove()
    assert not (tmp_path / "s").exists()


def test_segment_store_reads_copies_and_reports_torn_blocks(tmp_path):
    """Reads are mapped (a block's first row alone loads only that row) but return copies: a block
    written again afterwards does not change what was read; a block cut short on disk is an error
    naming the block, not a crash or silently short data."""
    store = io.SegmentStore(tmp_path / "s", block=4)
    data = np.arange(8 * 5, dtype=float).reshape(8, 5)
    store.write_rows("x", 0, data)
    first = store.read("x", 0, 4)
    edge = store.read("x", 4, 5)  # one row of the second block
    store.write("x", 0, -data[:4])
    store.write("x", 4, -data[4:])
    np.testing.assert_array_equal(first, data[:4])
    np.testing.assert_array_equal(edge, data[4:5])
    np.testing.assert_array_equal(store.read("x", 3, 5), -data[3:5])
    f = tmp_path / "s" / "x.00000001.npy"
    f.write_bytes(f.read_bytes()[:-16])  # the last two values lost
    with pytest.raises(io.FluxFileError, match="x.00000001.npy"):
        store.read("x", 4, 8)


def test_segment_store_writes_in_place_only_over_a_block_of_the_same_shape(tmp_path):
    """``in_place``: a block of the same shape and type is overwritten in its file (the same inode, read
    back exactly, earlier reads unchanged); a new block, another shape or another type, or a file that
    is not a readable block, is written whole as before."""
    store = io.SegmentStore(tmp_path / "s", block=4)
    data = np.arange(8 * 5, dtype=float).reshape(8, 5)
    store.write("x", 0, data[:4], in_place=True)  # no block yet: written whole
    f = tmp_path / "s" / "x.00000000.npy"
    inode = f.stat().st_ino
    before = store.read("x", 0, 4)
    store.write("x", 0, -data[:4], in_place=True)
    assert f.stat().st_ino == inode
    np.testing.assert_array_equal(store.read("x", 0, 4), -data[:4])
    np.testing.assert_array_equal(before, data[:4])
    store.write("x", 0, data[:3], in_place=True)  # fewer rows: a new file
    assert f.stat().st_ino != inode
    np.testing.assert_array_equal(store.read("x", 0, 3), data[:3])
    inode = f.stat().st_ino
    store.write("x", 0, data[:3].astype(np.float32), in_place=True)  # another type: a new file
    assert f.stat().st_ino != inode and store.read("x", 0, 3).dtype == np.float32
    f.write_bytes(b"torn")  # not a block at all: written whole, no error
    store.write("x", 0, data[:4], in_place=True)
    np.testing.assert_array_equal(store.read("x", 0, 4), data[:4])


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 5_000_000))
def test_default_budget_keeps_48_sample_blocks_until_its_cap(n_facets):
    """The default (time, facet) budget: 256 MB while that holds 48 samples of six float64 rows of
    ``n_facets`` (48 x 6 x 8 B = 2,304 B per facet: up to 116,508 facets), then what 48 samples need, up
    to 4096 MB (1,864,135 facets), then 4096 MB (fewer samples). The blocks it gives, counted here from
    the bytes: 48 or more samples up to the cap, and what fits 4 GB beyond."""
    mb = simulate.default_chunk_mb(n_facets)
    per_sample_mb = 6 * 8 * n_facets / 2**20
    if n_facets <= 116_508:
        assert mb == 256.0
    elif n_facets <= 1_864_135:
        assert mb == pytest.approx(48 * per_sample_mb, rel=1e-12)
    else:
        assert mb == 4096.0
    rows = simulate.block_rows(n_facets, mb * 2**20)
    fits = (4096 * 2**20) // (48 * n_facets)  # whole samples in 4 GB
    assert rows >= 48 if n_facets <= 1_864_135 else rows == (fits // 24 * 24 if fits >= 24 else fits)
    assert rows * per_sample_mb <= mb * (1 + 1e-12)  # within the budget


def test_case_budget_default_and_override(tmp_path):
    """A case without ``[output] chunk_mb`` gets the default of its mesh's size; one that sets it, that."""
    unset = tmp_path / "unset.toml"
    unset.write_text(
        CASE.format(name="u", facets=60, end="2019-01-03", chunk_mb=1, every=0).replace("chunk_mb = 1\n", "")
    )
    case = config.load_case(unset)
    assert case.output.chunk_mb is None
    assert simulate.chunk_bytes(case, 60) == 256.0 * 2**20
    assert simulate.chunk_bytes(case, 1_000_000) == 48 * 6 * 8 * 1_000_000
    case = _case(tmp_path, "set", chunk_mb=64.0)
    assert simulate.chunk_bytes(case, 1_000_000) == 64.0 * 2**20


def test_tiny_budget_gives_the_same_run(tmp_path):
    """Blocks of a few samples (a tiny chunk_mb) change nothing: the same fluxes and temperatures to
    rounding (uniform start and fixed spin-up: no block-wise means; the scattering solve of a different
    number of right-hand sides differs in the last bit, 1e-9 W m-2 / K is far below anything physical)."""
    a = runner.run_case(_case(tmp_path, "big"), tmp_path / "big.nc", progress=False)
    b = runner.run_case(_case(tmp_path, "tiny", chunk_mb=0.02), tmp_path / "tiny.nc", progress=False)
    da, db = io.open_run(a), io.open_run(b)
    assert simulate.block_rows(60, 0.02 * 2**20) < da.sizes["time"] // 4  # really several blocks
    for name in ("surface_temperature", "ir_incident", "solar_incident", "solar_direct", "spinup_ir_incident"):
        np.testing.assert_allclose(db[name].values, da[name].values, rtol=1e-12, atol=1e-9)
    assert not (tmp_path / "tiny.nc.partial").exists()
    # the run file is chunked along time and facet, and compressed
    import netCDF4

    with netCDF4.Dataset(b) as nc:
        var = nc["surface_temperature"]
        assert var.chunking() != "contiguous" and var.filters()["zlib"]


def test_streamed_replay_matches_in_memory(tmp_path):
    """Replay in time blocks (tiny budget, several facet batches) = replay held in memory."""
    run = io.open_run(runner.run_case(_case(tmp_path, "r"), tmp_path / "r.nc", progress=False))
    profiles = runner.resolve_profiles(["1300/1800", "rock"])
    ref, _ = simulate.replay_fluxes(run, profiles, initial_temperature=100.0, progress=False)
    got, _ = simulate.replay_fluxes(
        run, profiles, initial_temperature=100.0, progress=False, chunk_mb=0.01, chunk_columns=25
    )
    np.testing.assert_array_equal(got, ref)
    out = runner.replay_file(
        tmp_path / "r.nc",
        ["1300/1800", "rock"],
        initial_temperature=100.0,
        output=tmp_path / "rep.nc",
        progress=False,
        chunk_mb=0.01,
    )
    rep = io.open_replay(out)
    np.testing.assert_array_equal(rep["surface_temperature"].values, ref)
    assert list(rep["profile"].values) == ["1300/1800", "rock"]
    rep.close()


def test_memory_bounded_by_budget_not_run_length(tmp_path):
    """A run whose (time x facet) series are ~40x the chunk budget: the peak of traced allocations (numpy
    buffers) stays below the budget plus the radiation operator plus a fixed allowance, and does not grow
    when the record is 4x longer."""
    budget_mb, nf = 0.25, 300
    runner.run_case(
        _case(tmp_path, "warm", facets=nf, end="2019-01-03"), tmp_path / "warm.nc", progress=False
    )  # ephemeris tables, view-factor cache, numba: loaded before measuring
    peaks = []
    for end in ("2019-01-31", "2019-04-30"):
        case = _case(tmp_path, "m" + end, facets=nf, end=end, chunk_mb=budget_mb)
        tracemalloc.start()
        try:
            runner.run_case(case, tmp_path / f"m{end}.nc", progress=False)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    ds = io.open_run(tmp_path / "m2019-04-30.nc")
    whole = 5 * ds.sizes["time"] * nf * 8  # direct, solar, T, IR, spin-up: what a run used to hold
    assert whole > 15 * budget_mb * 2**20
    operator = 2 * (nf * nf * 8)  # F (dense-ish at 300 facets) and its scattering factorisation
    # allowance: solver columns (~10 (nf, nz) arrays), mesh, ephemeris sampling, the checkpoint state
    # (measured: 2.0 MB peak in all against 1.6 MB of budget + operator)
    allowance = 2 * 2**20
    assert peaks[1] < budget_mb * 2**20 + operator + allowance, peaks
    assert peaks[1] < 1.2 * peaks[0] + 2**20, peaks  # 4x the record, (almost) the same peak


@settings(max_examples=300, deadline=None)
@given(block=st.integers(1, 200_000), width=st.integers(1, 20_000))
def test_aligned_chunk_width_divides_the_pieces_or_keeps_the_size(block, width):
    """The facet extent of chunks written in pieces of ``block`` facets: a divisor of the block (so that
    every piece fills whole chunks) no wider than the size-based ``width`` and at least a quarter of it, or,
    where the block has no such divisor, ``width`` itself. Checked against a brute-force search."""
    got = io.aligned_width(block, width)
    divisors = [d for d in range(1, min(block, width) + 1) if block % d == 0]
    if block <= width:
        assert got == block
    elif 4 * max(divisors) >= width:
        assert got == max(divisors) and block % got == 0 and got <= width
    else:
        assert got == width


def test_pieces_of_a_facet_block_fill_whole_chunks(tmp_path):
    """A variable streamed in pieces of 2,000 facets (a distributed replay's chunks) over 20,000 facets is
    chunked 2,000 facets wide (not the size-based ~10,900, which 6 pieces would share); without pieces the
    size-based width stays; the values written piece by piece read back equal."""
    import netCDF4
    import xarray as xr

    nt, nf = 30, 20_000
    rng = np.random.default_rng(3)
    values = rng.uniform(40.0, 300.0, (2, nt, nf)).astype(np.float32)
    skeleton = xr.Dataset(coords={"facet": np.arange(nf)})
    spec = {"T": (("profile", "time", "facet"), (2, nt, nf), {"units": "K"}, "f4")}
    for block, width in ((2000, 2000), (None, io.chunk_shape((2, nt, nf), 1, 24, itemsize=4)[-1])):
        out = tmp_path / f"pieces_{block}.nc"
        with io.stream_dataset(skeleton, out, spec, time_rows=24, facet_block=block) as write:
            for f0 in range(0, nf, 2000):
                write("T", (slice(0, 2), slice(0, nt), slice(f0, f0 + 2000)), values[:, :, f0 : f0 + 2000])
        with netCDF4.Dataset(out) as nc:
            assert nc["T"].chunking() == [1, 24, width]
            np.testing.assert_array_equal(nc["T"][:], values)
    assert width > 2000


@settings(max_examples=40, deadline=None)
@given(
    nt=st.integers(1, 70),
    nf=st.integers(1, 3000),
    time_rows=st.integers(1, 30),
    row_piece=st.integers(1, 80),
    facet_piece=st.integers(1, 3500),
    compression=st.sampled_from(["zlib", "blosc_lz4"]),
    dtype=st.sampled_from(["f4", "f8"]),
)
def test_streamed_pieces_read_back_by_netcdf(
    tmp_path_factory, nt, nf, time_rows, row_piece, facet_piece, compression, dtype
):
    """Whatever the pieces (aligned with the chunks or not, edge chunks, one row, one facet), a streamed
    variable read back by netCDF-C/HDF5 (their own shuffle and inflate, independent of the writer's
    parallel shuffle + deflate) equals the array the pieces were cut from, and the global attributes
    added at the end are there. blosc_lz4 included: its HDF5 filter fails on chunks under 512 bytes, which
    are written with zlib instead."""
    import netCDF4
    import xarray as xr

    rng = np.random.default_rng(nt * 7919 + nf)
    values = (60.0 + 200.0 * rng.random((nt, nf))).astype(dtype)
    skeleton = xr.Dataset(coords={"facet": np.arange(nf)})
    spec = {"T": (("time", "facet"), (nt, nf), {"units": "K"}, dtype)}
    out = tmp_path_factory.mktemp("pieces") / "s.nc"
    with io.stream_dataset(skeleton, out, spec, time_rows=time_rows, compression=compression) as write:
        for a in range(0, nt, row_piece):
            for f in range(0, nf, facet_piece):
                write(
                    "T",
                    (slice(a, a + row_piece), slice(f, f + facet_piece)),
                    values[a : a + row_piece, f : f + facet_piece],
                )
        write.set_attrs({"note": "end", "flag": True, "timing_s": {"io": 1.5}, "skipped": None})
    with netCDF4.Dataset(out) as nc:
        got = nc["T"][:]
        assert not np.ma.is_masked(got)
        np.testing.assert_array_equal(np.asarray(got), values)
        filters = nc["T"].filters()
        assert filters["zlib"] or (compression == "blosc_lz4" and filters["blosc"])
        assert nc.getncattr("note") == "end" and nc.getncattr("flag") == 1
        assert json.loads(nc.getncattr("timing_s")) == {"io": 1.5} and "skipped" not in nc.ncattrs()


def test_streamed_file_interrupted_leaves_the_earlier_output(tmp_path):
    """An exception while chunks go in (the zlib path writes through h5py) leaves no file and does not
    touch an existing output; no temporary is left beside it."""
    import xarray as xr

    out = tmp_path / "run.nc"
    out.write_bytes(b"earlier result")
    spec = {"T": (("time", "facet"), (48, 500), {"units": "K"}, "f4")}
    with pytest.raises(RuntimeError, match="killed"):
        with io.stream_dataset(xr.Dataset(coords={"facet": np.arange(500)}), out, spec, overwrite=True) as write:
            write("T", (slice(0, 24), slice(None)), np.ones((24, 500)))
            raise RuntimeError("killed")
    assert out.read_bytes() == b"earlier result"
    assert [p.name for p in tmp_path.iterdir()] == ["run.nc"]


def test_without_h5py_netcdf4_writes_the_same_values(tmp_path, monkeypatch):
    """Where h5py is not installed the zlib series are written by netCDF4 alone: the same values and
    chunks as the parallel writer's file."""
    import netCDF4
    import xarray as xr

    rng = np.random.default_rng(11)
    values = rng.uniform(40.0, 300.0, (50, 3000)).astype(np.float32)
    spec = {"T": (("time", "facet"), values.shape, {"units": "K"}, "f4")}
    files = {}
    for label, missing in (("h5py", False), ("netcdf4", True)):
        if missing:
            monkeypatch.setattr(io, "_h5py", lambda: None)
        files[label] = tmp_path / f"{label}.nc"
        with io.stream_dataset(xr.Dataset(coords={"facet": np.arange(3000)}), files[label], spec) as write:
            for a in range(0, 50, 24):
                write("T", (slice(a, a + 24), slice(None)), values[a : a + 24])
    for path in files.values():
        with netCDF4.Dataset(path) as nc:
            np.testing.assert_array_equal(nc["T"][:], values)
            assert nc["T"].filters()["zlib"] and nc["T"].filters()["shuffle"]
            assert nc["T"].chunking() == [24, 3000]
