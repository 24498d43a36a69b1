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

    def fake_fit_starts(ctx, jobs, *_):
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

    def fake_fit_starts(ctx, jobs, *_):
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

    def fake_fit_starts(ctx, jobs, *_):
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


def test_starts_far_behind_after_the_first_rounds_stop_there(monkeypatch, model):
    """With a stage's ``drop`` (rounds, ratio), starts are fitted that many rounds; those above
    ratio times the lowest keep what they reached, the others go on from there to the end, as
    a fit never stopped would (the rounds counted on), their evaluations summed."""
    calls = []

    def fake_fit_rounds(model_, frame, start, options, dispatch, first_round=0):
        calls.append((float(start[0]), first_round, options.max_iterations))
        rounds = options.max_iterations - first_round
        # a start's energy after r rounds: its first number, less one per round
        return FrameResult(start - rounds, int(start[0]) - rounds, options.max_iterations, 10 * rounds)

    monkeypatch.setattr(search, "fit_rounds", fake_fit_rounds)
    monkeypatch.setattr(search, "full_energy", lambda model_, frame, params: int(params[0]))
    options = FitOptions()
    ctx = search.Context(model, None, options, search.solve_locally(model, None, options))
    jobs = [(np.full(35, e), "wide-round") for e in (102.0, 300.0, 150.0)]
    fits = search.fit_starts(ctx, jobs, drop=(2, 1.5))
    full = search.VARIANTS["wide-round"](options).max_iterations
    assert [f.energy for f in fits] == [102 - full, 298, 150 - full]  # 298 > 1.5 x 100: stopped
    assert [f.iterations for f in fits] == [full, 2, full]
    assert [f.evaluations for f in fits] == [10 * full, 20, 10 * full]
    assert [len(f.chains) for f in fits] == [2, 1, 2]
    assert all(f.variant == "wide-round" and f.start is s for f, (s, _) in zip(fits, jobs))
    assert sorted(c for c in calls if c[1] == 2) == [(100.0, 2, full), (148.0, 2, full)]
    assert search.fit_starts(ctx, [], drop=(2, 1.5)) == []  # every start remembered: nothing to fit
    calls.clear()
    plain = search.fit_starts(ctx, jobs)
    assert [f.energy for f in plain] == [102 - full, 300 - full, 150 - full] and len(calls) == 3


def test_the_search_and_the_actor_size_search_drop_starts_alike():
    """Both fit the voxel starts by the same stage, so the size search's fits are the search's."""
    assert search.SEARCH.stages[0] is search.WIDE_STARTS is search.WIDE.stages[0]
    assert search.WIDE_STARTS.drop is not None
