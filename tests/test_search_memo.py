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


def test_only_the_lowest_starts_are_fitted_the_other_way(monkeypatch, model):
    """A search fits every start one way of re-detecting limbs (wide-round), then fits again
    from their own starts only the WIDE_BOTH_STARTS fits of lowest score the other way."""
    fitted = []

    def fake_fit_starts(ctx, jobs):
        fitted.extend(jobs)
        return [FrameResult(np.asarray(s), 1000 + int(s[0]) * (7 if v == "wide-round" else 1), 1, 100, (), v,
                            np.asarray(s)) for s, v in jobs]

    monkeypatch.setattr(search, "fit_starts", fake_fit_starts)
    monkeypatch.setattr(search, "inversion_cost", lambda model, frame, params: 0.0)
    starts = tuple(np.full(35, float(k)) for k in (5, 0, 3, 1, 4, 2))
    ctx = search.Context(model, frame=None, options=FitOptions(), dispatch=None, starts=starts)
    schedule = search.Schedule(search.SEARCH.stages[:2])
    best = search.run_schedule(ctx, schedule)
    first_way = [s[0] for s, v in fitted if v == "wide-round"]
    other_way = [s[0] for s, v in fitted if v == "wide-all"]
    assert first_way == [5, 0, 3, 1, 4, 2]
    assert sorted(other_way) == sorted([0, 1, 2, 3][:search.WIDE_BOTH_STARTS])
    assert best.energy == 1000 and best.variant in ("wide-round", "wide-all")


def test_a_proposer_is_asked_once_per_fit_and_variants(monkeypatch, model):
    """A later stage whose best fit is still the one an earlier stage proposed from does not ask
    the same proposer again for the same variants (its starts are fitted already, and a limb
    search would run again); other variants still get their starts."""
    asked = []

    def fake_fit_starts(ctx, jobs):
        return [FrameResult(np.asarray(s) + 1.0, 1000, 1, 100, (), v, np.asarray(s)) for s, v in jobs]

    def probe(ctx, source, spent, own):
        asked.append(None if source is None else float(source.params[0]))
        return [np.full(35, 50.0)]  # fits to 51 at energy 1000: never lower than the start's fit

    monkeypatch.setattr(search, "fit_starts", fake_fit_starts)
    monkeypatch.setitem(search.PROPOSERS, "probe", probe)
    ctx = search.Context(model, frame=None, options=FitOptions(), dispatch=None, starts=(np.zeros(35),))
    start = search.Stage(("starts",))
    schedule = search.Schedule((start, search.Stage(("probe",)), search.Stage(("probe",)),
                                search.Stage(("probe",), ("polish",))))
    search.run_schedule(ctx, schedule)
    assert asked == [1.0, 1.0]  # the starts' fit (params 1): once for "track", once for "polish"
