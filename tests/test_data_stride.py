"""Frame strides (gns.data.stride): which data a model of one frame spacing can roll out on, the
frames it reads there (by hand, and as `gns convert --frame-stride` writes them), and the
messages."""

from __future__ import annotations

import numpy as np
import pytest
from data_helpers import assert_same, metadata_dict, random_walk, write_metadata
from gns.data import (
    at_frame_stride,
    convert,
    describe_frame_stride,
    frame_stride,
    open_dataset,
)
from gns.data.h5 import write_h5


@pytest.mark.parametrize(
    ("model_dt", "data_dt", "stride"),
    [
        (0.0075, 0.0025, 3),
        (0.0025 * 3, 0.0025, 3),  # what gns convert writes: 0.007500000000000001
        (0.0025, 0.0025, 1),
        (0.0075, 0.00125, 6),
        (0.0075, 0.0025 * (1 + 5e-7), 3),  # inside the relative 1e-6
        (None, 0.002, 1),  # a checkpoint that does not know its spacing reads every frame
    ],
)
def test_the_stride_is_the_whole_ratio_of_the_spacings(model_dt, data_dt, stride):
    assert frame_stride(model_dt, data_dt) == stride


def test_a_spacing_that_does_not_divide_the_models_step_is_refused_naming_both():
    with pytest.raises(ValueError) as refused:
        frame_stride(0.0075, 0.002)
    assert str(refused.value) == (
        "the model steps 7.5 ms at a time, the data's frames are 2 ms apart: 7.5 ms is not a "
        "whole multiple of 2 ms; the model rolls out on frames 7.5 ms apart or a whole fraction "
        "of that (3.75 ms, 2.5 ms, 1.875 ms, ...): write the data at such a spacing, or use a "
        "model trained at a whole multiple of 2 ms"
    )


def test_data_coarser_than_the_model_is_refused():
    with pytest.raises(ValueError) as refused:
        frame_stride(0.0075, 0.0225)
    assert str(refused.value).startswith(
        "the model steps 7.5 ms at a time, the data's frames are 22.5 ms apart: its frames are "
        "farther apart than the model's step; the model rolls out on frames 7.5 ms apart or a "
        "whole fraction of that"
    )


@pytest.mark.parametrize(
    ("model_dt", "data_dt", "shown"),
    [
        (0.0075, 0.0025 * (1 + 4e-6), "2.50001 ms"),  # just outside: 7 digits tell it apart
        (0.0075, 0.003, "3 ms"),
        (2.0, 0.8, "800 ms"),
        (3.0, 1.5 * 1.01, "1.515 s"),
    ],
)
def test_near_misses_are_refused_and_named_apart(model_dt, data_dt, shown):
    with pytest.raises(ValueError, match=f"the data's frames are {shown} apart"):
        frame_stride(model_dt, data_dt)


@pytest.mark.parametrize(("model_dt", "data_dt"), [(0.0, 0.0025), (0.0075, -1.0), (0.0075, np.nan)])
def test_spacings_that_are_not_positive_are_refused(model_dt, data_dt):
    with pytest.raises(ValueError, match="must be a positive number of seconds"):
        frame_stride(model_dt, data_dt)


def test_frames_from_0_with_their_context_as_many_as_every_phase_has():
    rng = np.random.default_rng(0)
    trajectory = random_walk(rng, 11, 5, context=2, material="particle", key=4)
    strided = at_frame_stride(trajectory, 3)
    # 11 frames: phases 0, 1 and 2 each have 3 frames (2, 5, 8 is the last phase's), so frame 9
    # of phase 0 is left out, as gns convert leaves it out.
    picked = np.array([0, 3, 6])
    np.testing.assert_array_equal(strided.positions, trajectory.positions[picked])
    np.testing.assert_array_equal(strided.step_context, trajectory.step_context[picked])
    np.testing.assert_array_equal(strided.particle_type, trajectory.particle_type)
    np.testing.assert_array_equal(strided.material_property, trajectory.material_property)
    assert (strided.key, strided.source) == (4, trajectory.source)
    last = at_frame_stride(trajectory, 3, phase=2)
    np.testing.assert_array_equal(last.positions, trajectory.positions[[2, 5, 8]])
    # A multiple of the stride loses nothing: 12 frames give 0, 3, 6, 9.
    whole = random_walk(rng, 12, 5)
    np.testing.assert_array_equal(at_frame_stride(whole, 3).positions, whole.positions[::3])
    assert at_frame_stride(trajectory, 1) is trajectory


@pytest.mark.parametrize(
    ("stride", "phase", "message"),
    [
        (0, 0, "frame stride must be a whole number >= 1, got 0"),
        (2.0, 0, "frame stride must be a whole number >= 1, got 2.0"),
        (True, 0, "frame stride must be a whole number >= 1, got True"),
        (3, 3, "phase must be a whole number from 0 to 2, got 3"),
        (3, -1, "phase must be a whole number from 0 to 2, got -1"),
        (12, 0, "frame stride 12 needs trajectories of at least 12 frames; trajectory 0 of "),
    ],
)
def test_bad_strides_and_phases_are_refused(stride, phase, message):
    trajectory = random_walk(np.random.default_rng(0), 11, 5)
    with pytest.raises(ValueError, match=message):
        at_frame_stride(trajectory, stride, phase=phase)


def test_convert_writes_the_frames_at_frame_stride_reads(tmp_path):
    rng = np.random.default_rng(1)
    items = [random_walk(rng, 14, 6, context=1, key=k) for k in range(2)]
    write_metadata(tmp_path / "native", metadata_dict(sequence_length=13))
    write_h5(tmp_path / "native/train.h5", items)
    write_h5(tmp_path / "native/test.h5", items)
    convert(tmp_path / "native", tmp_path / "strided", "h5", frame_stride=3)
    native = open_dataset(tmp_path / "native", "test")
    for split, phases in (("test", 1), ("train", 3)):
        written = open_dataset(tmp_path / "strided", split)
        expected = [at_frame_stride(t, 3, phase=p) for t in native for p in range(phases)]
        assert len(written) == len(expected)
        for ours, theirs in zip(expected, written, strict=True):
            # The reader numbers what it reads; the rest is the same, exactly.
            assert_same(type(ours)(ours.positions, ours.particle_type, ours.step_context), theirs)


@pytest.mark.parametrize(
    ("stride", "words"),
    [(2, "every 2nd frame"), (3, "every 3rd frame"), (11, "every 11th frame")],
)
def test_what_a_stride_does_in_words(stride, words):
    text = describe_frame_stride(0.0025, stride)
    assert text == (
        f"the data's frames are 2.5 ms apart, the model's steps {2.5 * stride:g} ms: {words}"
    )
    assert describe_frame_stride(0.0075, 1) == (
        "the data's frames are 7.5 ms apart, as the model's steps: every frame"
    )
