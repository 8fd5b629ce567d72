"""Trial container: validation and HDF5 round trip."""

import numpy as np
import pytest

from magenv.trial import Trial, TrialError


def test_hdf5_round_trip(tmp_path, make_kinematic_trial):
    trial = make_kinematic_trial(duration=2.0, disturbance_ut=10.0)
    trial.meta["note"] = "round trip"
    back = Trial.load(trial.save(tmp_path / "t.h5"))
    for key in ("gyr", "acc", "mag", "q_true", "score_mask"):
        assert np.array_equal(getattr(back, key), getattr(trial, key))
    for key in trial.truth:
        assert np.array_equal(back.truth[key], trial.truth[key])
    assert back.rate == trial.rate and back.name == trial.name and back.meta == trial.meta
    assert (back.field_norm, back.field_dip) == (trial.field_norm, trial.field_dip)


def test_slice_keeps_channels(make_kinematic_trial):
    trial = make_kinematic_trial(duration=2.0)
    part = trial.slice(10, 110)
    assert part.n == 100 and part.truth["stationary"].shape == (100,)
    assert np.array_equal(part.gyr, trial.gyr[10:110])


def _arrays(n=10):
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return dict(gyr=np.zeros((n, 3)), acc=np.zeros((n, 3)), mag=np.zeros((n, 3)), q_true=q)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(gyr=np.zeros((10, 2))), "gyr must have shape"),
        (dict(mag=np.full((10, 3), np.nan)), "mag contains NaN"),
        (dict(rate=0.0), "rate must be a sampling rate from 1 to 100000 Hz, got 0.0"),
        (dict(score_mask=np.ones(9, bool)), "score_mask must have shape"),
        (dict(truth={"stationary": np.zeros(3)}), "truth channel 'stationary' has 3 rows"),
    ],
)
def test_bad_input_names_the_problem(change, message):
    kwargs = dict(name="x", rate=100.0, field_norm=46.0, field_dip=49.6, **_arrays())
    kwargs.update(change)
    with pytest.raises(TrialError, match=message):
        Trial(**kwargs)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(TrialError, match="no such file"):
        Trial.load(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    with pytest.raises(TrialError, match="junk.h5: not an HDF5 file"):
        Trial.load(junk)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("field_norm", 0.0, r"field_norm must be a finite number in \(0, 1000\], got 0.0"),
        ("field_norm", np.nan, "field_norm must be a finite number in .*, got nan"),
        ("field_norm", -40.0, "got -40.0"),
        ("field_norm", np.inf, "got inf"),
        ("field_dip", 500.0, r"field_dip must be a finite number in \[-90, 90\], got 500.0"),
        ("field_dip", np.nan, "field_dip must be a finite number"),
        ("field_norm", "46", "field_norm must be a number"),
    ],
)
def test_an_impossible_field_is_refused_whenever_it_is_set(field, value, message, tmp_path, make_kinematic_trial):
    """At construction, by assignment afterwards, and from a file: no env or filter is handed it."""
    import dataclasses

    import h5py

    kwargs = dict(name="x", rate=100.0, field_norm=46.0, field_dip=49.6, **_arrays())
    with pytest.raises(TrialError, match=message):
        Trial(**{**kwargs, field: value})
    trial = make_kinematic_trial(duration=1.0)
    with pytest.raises(TrialError, match=message):
        setattr(trial, field, value)
    assert (trial.field_norm, trial.field_dip) == (46.0, 49.6)  # unchanged
    with pytest.raises(TrialError, match=message):
        dataclasses.replace(trial, **{field: value})
    if isinstance(value, float):
        path = trial.save(tmp_path / "t.h5")
        with h5py.File(path, "a") as f:
            f.attrs[field] = value
        with pytest.raises(TrialError, match=f"t.h5: .*{message}"):
            Trial.load(path)


def test_a_good_field_is_stored_as_a_float(make_kinematic_trial):
    trial = make_kinematic_trial(duration=1.0)
    trial.field_norm, trial.field_dip = np.float32(50), -90
    assert (trial.field_norm, trial.field_dip) == (50.0, -90.0) and type(trial.field_dip) is float
