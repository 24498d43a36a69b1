"""Frame offsets between cameras from the silhouettes (common.sync, mocap sync)."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from common.sequence import load_sequence
from common.sync import CameraSync, estimate_offsets, judged_frames, peak
from server.cli import main

from conftest import WALK_CLIP, load_tool

pytestmark = pytest.mark.timeout(240)

FRAMES = 60


@pytest.fixture(scope="module")
def walk(tmp_path_factory, model):
    """A 60-frame walk, 6 cameras at 320x240, silhouettes as rendered (read-only)."""
    from common.camera import circle_studio
    from common.synth import SynthOptions, synthesize

    out = tmp_path_factory.mktemp("sync") / "walk"
    synthesize(model, circle_studio(6, 320, 240), WALK_CLIP, out,
               SynthOptions(frames=FRAMES, start=1, step=4, noise="none", surface="skinned", seed=0))
    return out


TRIALS = load_tool("sync_trials")  # a camera put out of step in memory or in a copy, as the trials do
late_mask_of = TRIALS.late_mask_of


def test_a_camera_out_of_step_is_found_and_the_others_kept(walk):
    seq = load_sequence(walk, clean_masks=False)
    estimate = estimate_offsets(seq.studio, late_mask_of(seq, {0: 2}), len(seq.frames))
    assert estimate.cameras[0].resolved and estimate.cameras[0].offset == 2
    assert all(c.offset == 0 for c in estimate.cameras[1:])
    assert sum(c.resolved for c in estimate.cameras) >= 3  # the views across the walk tell frames apart
    # in step, nothing moves: a camera that cannot tell keeps 0 and says so
    in_step = estimate_offsets(seq.studio, late_mask_of(seq, {}), len(seq.frames))
    assert in_step.offsets == {c.name: 0 for c in seq.studio}
    assert [c.camera for c in in_step.cameras if not c.resolved] == in_step.unresolved


def test_two_cameras_off_either_way(walk):
    seq = load_sequence(walk, clean_masks=False)
    estimate = estimate_offsets(seq.studio, late_mask_of(seq, {0: -3, 3: 2}), len(seq.frames))
    assert estimate.offsets["cam1"] == -3 and estimate.offsets["cam4"] == 2
    assert all(c.offset == 0 for k, c in enumerate(estimate.cameras) if k not in (0, 3))


def test_a_still_actor_tells_nothing(walk):
    seq = load_sequence(walk, clean_masks=False)
    still = seq.raw_silhouettes(seq.frames[0])
    estimate = estimate_offsets(seq.studio, lambda k, i: still[k], len(seq.frames))
    assert all(not c.resolved and c.offset == 0 for c in estimate.cameras)


def test_the_peak_must_beat_its_neighbours_frame_by_frame():
    clear = {-1: np.array([0.5, 0.52, 0.51]), 0: np.array([0.6, 0.61, 0.62]), 1: np.array([0.55, 0.56, 0.57])}
    assert peak(clear) == (0, True)
    noisy = {-1: np.array([0.5, 0.7, 0.5]), 0: np.array([0.6, 0.6, 0.61]), 1: np.array([0.7, 0.5, 0.5])}
    assert peak(noisy) == (0, False)
    at_edge = {0: np.array([0.5, 0.51]), 1: np.array([0.6, 0.62])}  # the last offset tried: it may rise beyond
    assert peak(at_edge) == (1, False)
    tie = {-1: np.array([0.6, 0.6]), 0: np.array([0.5, 0.5]), 1: np.array([0.6, 0.6])}
    assert peak(tie)[0] == -1  # the same score either side: the first found nearest 0
    assert CameraSync("cam1", 0, {0: 0.5}, False).resolved is False


def test_judged_frames_stay_inside_the_take():
    frames = judged_frames(60, 5, 24)
    assert frames[0] >= 10 and frames[-1] <= 49 and len(frames) == 24
    with pytest.raises(ValueError, match="at least 21"):
        judged_frames(20, 5, 24)


def late_copy(walk, tmp_path, camera: str, late: int):
    """A copy of the walk whose ``camera`` is out of step by ``late`` (file j holds frame j - late)."""
    TRIALS.late_copy(walk, tmp_path / "late", camera, late)
    return tmp_path / "late"


def test_mocap_sync_prints_the_offset_to_import_with(walk, tmp_path, capsys):
    seq = late_copy(walk, tmp_path, "cam1", 2)
    assert main(["sync", str(seq)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("cam1  +2  agreement")
    assert "import again with: --offset cam1=2" in out
    assert main(["sync", str(seq), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["offsets"]["cam1"] == 2 and report["frame_spacing"] == 1
    assert all(report["offsets"][c] in (0, None) for c in ("cam2", "cam3", "cam4", "cam5", "cam6"))
    assert {c for c, o in report["offsets"].items() if o is None} <= set(report["unresolved"])


def test_mocap_sync_counts_offsets_in_the_sequences_frames(walk, tmp_path, capsys):
    seq = late_copy(walk, tmp_path, "cam1", 2)
    meta = json.loads((seq / "sequence.json").read_text())
    meta["frames"] = meta["frames"][::2]  # every other frame: cam1 is one step late
    (seq / "sequence.json").write_text(json.dumps(meta))
    assert main(["sync", str(seq), "--max-offset", "3", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frame_spacing"] == 2 and report["offsets"]["cam1"] == 2


def test_mocap_sync_bad_input(walk, tmp_path, capsys):
    seq = tmp_path / "seq"
    shutil.copytree(walk, seq)
    assert main(["sync", str(seq), "--max-offset", "20"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "too few to try offsets of up to 20 frames" in err and "--max-offset" in err
    shutil.rmtree(seq / "silhouettes")
    assert main(["sync", str(seq)]) == 2
    assert "silhouettes" in capsys.readouterr().err


def test_mocap_sync_with_frames_left_out(walk, tmp_path, capsys):
    """A sequence imported with --missing-frames skip lacks some frame numbers: the frames that
    would need them are not judged, the rest are."""
    seq = late_copy(walk, tmp_path, "cam1", 2)
    meta = json.loads((seq / "sequence.json").read_text())
    meta["frames"] = [f for f in meta["frames"] if f not in (20, 33)]
    (seq / "sequence.json").write_text(json.dumps(meta))
    assert main(["sync", str(seq), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frame_spacing"] == 1 and report["offsets"]["cam1"] == 2


def estimate_of(*cameras):
    """A SyncEstimate of (name, offset, resolved, judged) cameras, scores peaked at the offset."""
    from common.sync import SyncEstimate

    return SyncEstimate(tuple(CameraSync(n, o, {d: 0.9 - 0.05 * abs(d - o) for d in range(-3, 4)}, r, j)
                              for n, o, r, j in cameras), tuple(range(24)))


def test_what_sync_prints_to_import_with():
    from server.commands.sync import report, report_lines

    found = estimate_of(("cam1", 0, True, 24), ("cam2", 2, True, 24), ("cam3", 0, True, 24), ("cam4", 0, False, 24))
    lines = report_lines(found, 1, {"cam2": -10, "cam3": 1}, 3)
    # the offset to import with is the import's and the one found together; the others' kept
    assert lines[-1] == "import again with: --offset cam2=-8 cam3=1"
    assert report(found, 1, {"cam2": -10}, 0)["import_offsets"] == {"cam1": 0, "cam2": -8, "cam3": 0}
    # two cameras that tell: either may be the one out of step
    two = estimate_of(("cam1", 0, True, 24), ("cam2", 0, False, 24), ("cam3", 1, True, 24), ("cam4", 0, False, 24))
    lines = report_lines(two, 1, {}, 3)
    assert "only 2 cameras tell their offset" in lines[-2] and lines[-1].startswith("not sharp, check by eye")
    # the best at the end of the offsets tried, and frames that could not be judged
    edge = estimate_of(("cam1", 3, False, 24), ("cam2", 0, True, 24), ("cam3", 0, True, 1), ("cam4", 0, True, 24))
    lines = report_lines(edge, 1, {}, 3)
    assert "try a larger --max-offset" in lines[0] and "no frame to judge" in lines[2]
    # nothing told: in a take long enough, the actor's doing; in a short one, the frames judged
    blind = estimate_of(("cam1", 0, False, 24), ("cam2", 0, False, 24), ("cam3", 0, False, 24))
    assert report_lines(blind, 1, {}, 3)[-1].endswith("the actor hardly moves in these frames")
    short = replace(blind, frames=(0, 1, 2, 3))
    assert report_lines(short, 1, {}, 2, 24)[-1] == (
        "no camera's offset could be told: only 4 frames could be judged (of --frames 24; a take needs 4 "
        "frames at each end beyond those judged): a longer stretch of the take would tell more")
    # frames missing in a camera as well: its own line says so, and the take's length is not blamed
    gaps = replace(estimate_of(("cam1", 0, False, 24), ("cam2", 0, False, 1)), frames=(0, 1, 2, 3))
    assert report_lines(gaps, 1, {}, 2, 24)[-1] == "no camera's offset could be told"


def test_offsets_are_stated_against_the_most_common():
    from common.sync import most_common

    assert most_common([0, 0, 0, 0, 2, 2, 2, 2]) == 0
    assert most_common([0, 0, 0, 1, 2, 3, 4, 5]) == 0
    assert most_common([3, 3, 3, 0, 1]) == 3
    assert most_common([2, 2, -1, -1]) == -1
