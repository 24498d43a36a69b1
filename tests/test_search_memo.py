"""Fits already made of a frame (the actor-size search's) are reused by a later schedule on the
same frame, and change nothing: the same poses, energies and evaluation counts as fitting again."""
import numpy as np
import pytest

from common.fitting import FitOptions, FrameResult
from common import search


def _ctx(model):
    return search.Context(model, frame=None, options=FitOptions(), dispatch=None, starts=(np.zeros(35), np.ones(35)))


def test_a_remembered_start_is_not_fitted_again(monkeypatch, model):
    fitted = []

    def fake_fit_starts(ctx, jobs):
        fitted.extend(jobs)
        return [FrameResult(np.asarray(s), int(np.sum(s)) + 10, 1, 100, (), v) for s, v in jobs]

    monkeypatch.setattr(search, "fit_starts", fake_fit_starts)
    schedule = search.Schedule((search.Stage(("starts",), ("track",)),))
    memo = {}
    first = search.run_schedule(_ctx(model), schedule, memo=memo)
    assert len(fitted) == 2 and len(memo) == 2
    again = search.run_schedule(_ctx(model), schedule, memo=memo)
    assert len(fitted) == 2  # nothing fitted the second time
    plain = search.run_schedule(_ctx(model), schedule)
    for got in (again, plain):
        assert np.array_equal(got.params, first.params) and got.energy == first.energy
        assert got.evaluations == first.evaluations  # what the frame's fits cost, wherever they were made


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_first_frame_search_after_the_actor_size_search_is_unchanged(model, small_sequence):
    from common.proposals import voxel_starts
    from common.sequence import load_sequence
    from server.session import choose_actor_scale, frame_data

    seq = load_sequence(small_sequence)
    options = FitOptions()
    size = choose_actor_scale(model, seq, options)
    assert size.scale == 1.0 and len(size.memo) >= len(size.starts)
    frame = seq.frames[0]
    data = frame_data(model, seq, frame)
    dispatch = search.solve_locally(model, data, options, frame)
    plain = search.search_frame(model, data, voxel_starts(model, data), options, dispatch, frame)
    reused = search.search_frame(model, data, size.starts, options, dispatch, frame, memo=dict(size.memo))
    assert np.array_equal(reused.params, plain.params)
    assert reused.energy == plain.energy and reused.evaluations == plain.evaluations
