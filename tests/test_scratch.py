"""The disk a run needs (issue 24: a million facets on one machine): the scratch store's peak measured
from its files during real runs against :func:`runner.scratch_estimate`, run.nc's series against the
file's own variables, and a run refused before any work when the output's disk cannot hold it."""

import os
from collections import namedtuple

import numpy as np
import pytest

from crater_thermal import config, io, runner
from crater_thermal.errors import DiskSpaceError

CASE = """
name = "{name}"
[crater]
kind = "crater"
diameter_km = 2.0
facets = 120
[location]
lat_deg = -85.0
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "2019-01-05"
{period}
[steps]
flux_step_hours = 4.0
{steps}
[surface]
albedo = 0.12
emissivity = 0.98
{surface}
[output]
chunk_mb = 0.05
save_spinup_fluxes = {save}
"""

#: spin-up and IR-coupling variants: every way the store is filled
VARIANTS = {
    "periodic_lagged": (
        'spinup = "periodic"\nspinup_days = 29.53\nperiodic_tol_K = 0.05\nspinup_ir = "lagged"',
        "",
        "",
    ),
    "periodic_coupled": (
        'spinup = "periodic"\nspinup_days = 29.53\nperiodic_tol_K = 0.05\nspinup_ir = "coupled"',
        "",
        "",
    ),
    "fixed_incidence": ('spinup = "fixed"\nspinup_days = 3.0', "", 'albedo_model = "hayne2017"'),
    "relaxed": ('spinup = "periodic"\nspinup_days = 29.53\nperiodic_tol_K = 0.05', 'ir_coupling = "relaxed"', ""),
    "no_spinup": ('spinup = "fixed"\nspinup_days = 0.0\ninitial_temperature_K = 150.0', "", ""),
}


def _case(tmp_path, variant: str, save: bool = True):
    period, steps, surface = VARIANTS[variant]
    path = tmp_path / f"{variant}.toml"
    text = CASE.format(name=variant, period=period, steps=steps, surface=surface, save=str(save).lower())
    path.write_text(text)
    return config.load_case(path)


def _data_bytes(folder) -> int:
    """Bytes of the arrays in a store's block files [B], from each .npy header (shape and type): the
    headers themselves and the markers are not data."""
    total = 0
    for entry in os.scandir(folder):
        if not entry.name.endswith(".npy"):
            continue
        with open(entry.path, "rb") as fh:
            major, _ = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(fh)
        total += int(np.prod(shape)) * np.dtype(dtype).itemsize
    return total


Measured = namedtuple("Measured", "peak series out case")


def _measure(tmp_path, monkeypatch, variant: str, save: bool = True) -> Measured:
    """A run of ``variant`` with the store's data bytes taken after every write, rename and drop."""
    case = _case(tmp_path, variant, save)
    peak = {"B": 0}
    write, rename, drop = io.SegmentStore.write, io.SegmentStore.rename, io.SegmentStore.drop

    def seen(store):
        peak["B"] = max(peak["B"], _data_bytes(store.folder))

    def write_seen(self, *a, **k):
        write(self, *a, **k)
        seen(self)

    def rename_seen(self, *a, **k):
        rename(self, *a, **k)
        seen(self)

    def drop_seen(self, *a, **k):
        drop(self, *a, **k)
        seen(self)

    monkeypatch.setattr(io.SegmentStore, "write", write_seen)
    monkeypatch.setattr(io.SegmentStore, "rename", rename_seen)
    monkeypatch.setattr(io.SegmentStore, "drop", drop_seen)
    out = runner.run_case(case, tmp_path / f"{variant}.nc", progress=False)
    ds = io.open_run(out)
    series = sum(v.size * v.dtype.itemsize for v in ds.data_vars.values() if v.dims[-1:] == ("facet",) and v.ndim == 2)
    shape = (ds.sizes["facet"], ds.sizes.get("spinup_time", 0), ds.sizes["time"])
    ds.close()
    return Measured(peak["B"], series, shape, case)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_scratch_estimate_bounds_the_store_measured_in_a_run(tmp_path, monkeypatch, variant):
    """The store's peak, measured from its files after every change during a run of each spin-up and
    coupling path, is within the estimate, and the estimate is no more than 10 % above it (the sunlight
    of every sample, the spin-up's series, then the record's rows: counted exactly, a block's rounding
    aside); run.nc's (time|spinup_time, facet) series, read from the file, are what the estimate counts."""
    m = _measure(tmp_path, monkeypatch, variant)
    nf, ns, nr = m.out
    coupling = "relaxed" if variant == "relaxed" else m.case.steps.ir_coupling
    est = runner.scratch_estimate(m.case, nf, ns, nr, coupling)
    assert 0 < m.peak <= est["store"] <= 1.10 * m.peak, (m.peak, est)
    # run.nc: the series of both windows, as the file holds them (uncompressed sizes)
    assert m.series == est["run_nc"], (m.series, est)


def test_lagged_spinup_leaves_only_the_saved_ir_in_the_store(tmp_path, monkeypatch):
    """The lagged start's own series go when it ends: the last input is renamed the saved spin-up IR (no
    copy), the others deleted, so the record's store is the sunlight, that IR and its rows; without
    saved spin-up fluxes nothing of the spin-up stays, its sunlight included (whole blocks before the
    record's first row)."""
    seen = []
    start = runner._start_of_record

    def after_start(case, fc, *a, **k):
        out = start(case, fc, *a, **k)
        names = [e.name.split(".")[0] for e in os.scandir(fc.store.folder) if e.name.endswith(".npy")]
        block, n_all = fc.store.block, len(fc.sun_dirs)
        # the sunlight's blocks that must stay: every one holding a row of the record
        kept = -(-n_all // block) - (fc.record_offset // block if not case.output.save_spinup_fluxes else 0)
        seen.append((sorted(set(names)), names.count("direct"), names.count("solar"), kept))
        return out

    monkeypatch.setattr(runner, "_start_of_record", after_start)
    for save in (True, False):
        runner.run_case(_case(tmp_path, "periodic_lagged", save), tmp_path / f"lag_{save}.nc", progress=False)
    assert seen[0][0] == ["T", "direct", "ir", "solar", "spin_ir"], seen
    assert seen[1][0] == ["T", "direct", "ir", "solar"], seen
    # without saved spin-up fluxes the spin-up's sunlight goes too (the blocks before the record's)
    for _, direct, solar, kept in seen:
        assert direct == solar == kept, seen
    assert seen[1][3] < seen[0][3], seen


Usage = namedtuple("Usage", "total used free")


def _disk_of(monkeypatch, free):
    """``shutil.disk_usage`` as the runner sees it: ``free(estimate)`` bytes free, from the estimate the
    run itself makes just before it asks (so the sizes are the run's own)."""
    est = {}
    estimate = runner.scratch_estimate

    def spy(*a, **k):
        est.update(estimate(*a, **k))
        return dict(est)

    monkeypatch.setattr(runner, "scratch_estimate", spy)
    monkeypatch.setattr(runner.shutil, "disk_usage", lambda p: Usage(10**13, 0, free(est)))
    return est


def _no_operator(built):
    def fail(*a, **k):
        built.append(1)
        raise AssertionError("the operator was built")

    return fail


def test_a_run_the_disk_cannot_hold_is_refused_before_any_work(tmp_path, monkeypatch):
    """With less free space than the store's peak the run stops at once (before the operator, the horizon
    map and the sunlight) with a one-line DiskSpaceError naming the space needed and what to do; no
    scratch store is left and an existing output is kept. With room for the store but not for run.nc
    as well, it warns and runs."""
    case = _case(tmp_path, "periodic_lagged")
    out = tmp_path / "kept.nc"
    out.write_bytes(b"an earlier result")
    built = []
    _disk_of(monkeypatch, lambda est: est["store"] - 1)
    monkeypatch.setattr(runner.simulate, "case_operator_and_horizons", _no_operator(built))
    with pytest.raises(DiskSpaceError) as err:
        runner.run_case(case, out, overwrite=True, progress=False)
    msg = str(err.value)
    assert "\n" not in msg and "GB of scratch" in msg and "GB free" in msg and "-o" in msg, msg
    assert not built and not (tmp_path / "kept.nc.partial").exists()
    assert out.read_bytes() == b"an earlier result"
    monkeypatch.undo()
    est = _disk_of(monkeypatch, lambda est: (est["store"] + est["total"]) // 2)
    with pytest.warns(UserWarning, match="may not fit"):
        runner.run_case(case, tmp_path / "warned.nc", progress=False)
    ds = io.open_run(tmp_path / "warned.nc")
    assert est["total"] > est["store"] > 0 and ds.sizes["time"] > 0
    ds.close()


def test_cli_refuses_a_run_the_disk_cannot_hold_with_exit_code_2(tmp_path, monkeypatch, capsys):
    """The command line: one line on stderr, exit code 2, no traceback, the output not written."""
    from crater_thermal import cli

    case = _case(tmp_path, "periodic_lagged")
    built = []
    _disk_of(monkeypatch, lambda est: est["store"] // 3)
    monkeypatch.setattr(runner.simulate, "case_operator_and_horizons", _no_operator(built))
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", str(case.path), "-o", str(tmp_path / "out.nc")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: this run needs ~") and "\n" not in err and "Traceback" not in err, err
    assert not built and not (tmp_path / "out.nc").exists()
