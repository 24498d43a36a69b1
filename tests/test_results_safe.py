"""Results are never lost: earlier results refused unless --resume/--overwrite, checked inputs
before any write, atomic files, staged folders, --resume that checks what it continues, and
options whose ranges are checked (issue: "Never lose a result, refuse bad input cleanly")."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from server.cli import main
from server.output import check_folder_target, replace_file, staged_folder
from common.errors import UserError

pytestmark = pytest.mark.timeout(240)

FAST = ["--iterations", "1", "--refine-passes", "0", "--turn-hypotheses", "0", "--polish-iterations", "0",
        "--quiet"]


def run(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def one_error_line(err: str, *names: str) -> str:
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("warning:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


def snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def seq(tmp_path, small_sequence) -> Path:
    out = tmp_path / "seq"
    shutil.copytree(small_sequence, out)
    return out


@pytest.fixture
def fitted(tmp_path, seq, capsys) -> Path:
    out = tmp_path / "res"
    code, err = run(capsys, "fit", seq, "--out", out, "--frames", "2", *FAST)
    assert code == 0, err
    return out


def test_an_earlier_result_is_refused_and_kept(fitted, seq, capsys):
    before = snapshot(fitted)
    code, err = run(capsys, "fit", seq, "--out", fitted, *FAST)
    assert code == 2
    one_error_line(err, str(fitted), "--resume", "--overwrite")
    assert snapshot(fitted) == before


def test_a_failing_overwrite_leaves_the_earlier_result(fitted, seq, capsys):
    """The issue's case: a frame file missing is found before poses.jsonl is touched."""
    before = snapshot(fitted)
    (seq / "silhouettes" / "cam3" / "000002.png").unlink()
    code, err = run(capsys, "fit", seq, "--out", fitted, "--overwrite", *FAST)
    assert code == 2
    one_error_line(err, "cam3", "000002.png")
    assert snapshot(fitted) == before


def test_overwrite_replaces_the_result_and_what_was_made_from_it(fitted, seq, capsys):
    (fitted / "report.html").write_text("old report")
    code, err = run(capsys, "fit", seq, "--out", fitted, "--overwrite", "--frames", "1", *FAST)
    assert code == 0, err
    assert len((fitted / "poses.jsonl").read_text().splitlines()) == 1
    assert json.loads((fitted / "summary.json").read_text())["frames"] == 1
    assert not (fitted / "report.html").exists()
    assert not list(fitted.glob(".*partial*"))


def test_a_run_refused_before_its_first_frame_leaves_nothing_in_the_way(tmp_path, seq, capsys):
    """--init truth without truth is refused before the folder is touched; and a folder that
    holds only run.json (a run stopped before its first frame) is no result: a corrected
    command goes ahead without --overwrite."""
    (seq / "truth.jsonl").unlink()
    out = tmp_path / "res"
    code, err = run(capsys, "fit", seq, "--out", out, "--init", "truth", "--frames", "1", *FAST)
    assert code == 2
    one_error_line(err, "--init truth", "truth.jsonl")
    assert not out.exists()
    out.mkdir()
    (out / "run.json").write_text("{}")
    code, err = run(capsys, "fit", seq, "--out", out, "--init", "standing", "--frames", "1", *FAST)
    assert code == 0, err
    assert len((out / "poses.jsonl").read_text().splitlines()) == 1
    assert json.loads((out / "run.json").read_text())["init"] == "standing"


def test_out_naming_a_file_is_one_line(tmp_path, seq, capsys):
    target = tmp_path / "a_file"
    target.write_text("keep me")
    code, err = run(capsys, "fit", seq, "--out", target, *FAST)
    assert code == 2
    one_error_line(err, str(target), "is a file")
    assert target.read_text() == "keep me"


@pytest.fixture
def read_only_dir(tmp_path):
    """A folder nobody can write to: a read-only tmpfs as root (root ignores modes), else mode 0555."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(folder)],
                             capture_output=True, timeout=10).returncode == 0
    if not mounted:
        pytest.skip("root without mount rights: no read-only folder to test with")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True, timeout=10)


def test_read_only_output_is_refused_before_fitting(read_only_dir, seq, capsys):
    code, err = run(capsys, "fit", seq, "--out", read_only_dir / "res", *FAST)
    assert code == 2
    one_error_line(err, "not writable")


def test_resume_continues_a_valid_prefix_with_the_same_poses(tmp_path, seq, capsys):
    whole = tmp_path / "whole"
    assert run(capsys, "fit", seq, "--out", whole, *FAST)[0] == 0
    part = tmp_path / "part"
    assert run(capsys, "fit", seq, "--out", part, *FAST)[0] == 0
    lines = (part / "poses.jsonl").read_text().splitlines(keepends=True)
    (part / "poses.jsonl").write_text(lines[0] + lines[1][:40])  # a crash while frame 1 was written
    code, err = run(capsys, "fit", seq, "--out", part, "--resume", *FAST)
    assert code == 0, err
    params = [[json.loads(line)["params"] for line in (d / "poses.jsonl").read_text().splitlines()]
              for d in (whole, part)]
    assert params[0] == params[1]


def test_resume_with_other_options_says_which(fitted, seq, capsys):
    before = snapshot(fitted)
    code, err = run(capsys, "fit", seq, "--out", fitted, "--resume", *FAST[:-3], "--polish-iterations", "2",
                    "--quiet")
    assert code == 2
    one_error_line(err, "--resume", "polish_iterations 2 (was 0)")
    assert snapshot(fitted) == before


def test_resume_refuses_a_corrupt_middle_line(tmp_path, seq, capsys):
    out = tmp_path / "res"
    assert run(capsys, "fit", seq, "--out", out, *FAST)[0] == 0
    lines = (out / "poses.jsonl").read_text().splitlines(keepends=True)
    (out / "poses.jsonl").write_text(lines[0] + "{not json\n" + lines[2])
    before = snapshot(out)
    code, err = run(capsys, "fit", seq, "--out", out, "--resume", *FAST)
    assert code == 2
    one_error_line(err, "poses.jsonl", "line 2")
    assert snapshot(out) == before
    code, err = run(capsys, "export", out, "--format", "csv", "--out", tmp_path / "m.csv")
    assert code == 2
    one_error_line(err, "poses.jsonl", "line 2")


@pytest.mark.parametrize("argv, names", [
    (["--frames", "-1"], ["--frames", ">= 1"]),
    (["--frames", "0"], ["--frames", ">= 1"]),
    (["--set", "fit.grid_range=nan"], ["--set", "[fit] grid_range", ">= 0"]),
    (["--set", "fit.grid_range=-1"], ["--set", "[fit] grid_range", ">= 0"]),
    (["--iterations", "0"], ["--iterations"]),
    (["--refine-hops", "-2"], ["--refine-hops"]),
    (["--set", "fit.turn_step=inf"], ["--set", "[fit] turn_step"]),
    (["--set", "fit.grid_stepz=3"], ["--set", "did you mean 'fit.grid_steps'"]),
    (["--set", "grid_steps"], ["--set", "SECTION.KEY=VALUE"]),
    (["--clients", "-1"], ["--clients"]),
])
def test_fit_option_ranges(tmp_path, seq, capsys, argv, names):
    code, err = run(capsys, "fit", seq, "--out", tmp_path / "res", *argv)
    assert code == 2
    one_error_line(err, *names)
    assert not (tmp_path / "res").exists()


def test_fewer_than_three_cameras_warn(tmp_path, capsys):
    seq = tmp_path / "two"
    assert run(capsys, "synth", "--out", seq, "--cameras", "2", "--frames", "1", "--size", "80x60", "--quiet")[0] == 0
    code, err = run(capsys, "fit", seq, "--out", tmp_path / "res", *FAST)
    assert code == 0, err
    assert "warning: 2 camera(s)" in err and "858 mm worst" in err


def test_synth_refuses_a_folder_in_use_and_replaces_it_whole(tmp_path, capsys):
    out = tmp_path / "seq"
    common = ["synth", "--out", out, "--cameras", "2", "--size", "80x60", "--quiet"]
    assert run(capsys, *common, "--frames", "3")[0] == 0
    before = snapshot(out)
    code, err = run(capsys, *common, "--frames", "2")
    assert code == 2
    one_error_line(err, str(out), "--overwrite")
    assert snapshot(out) == before
    assert run(capsys, *common, "--frames", "2", "--overwrite")[0] == 0
    assert sorted(p.name for p in (out / "silhouettes" / "cam1").iterdir()) == ["000000.png", "000001.png"]
    assert not list(tmp_path.glob(".*"))


def test_a_failed_staged_build_leaves_the_old_folder(tmp_path):
    out = tmp_path / "folder"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with staged_folder(out) as staged:
            (staged / "new.txt").write_text("half")
            raise RuntimeError("the run failed")
    assert [p.name for p in out.iterdir()] == ["old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["folder"]
    with staged_folder(out, merge=True) as staged:
        (staged / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt", "old.txt"]


def test_a_failed_file_write_leaves_the_old_file(tmp_path):
    path = tmp_path / "summary.json"
    path.write_text("old")

    def broken(tmp: Path) -> None:
        tmp.write_text("half")
        raise OSError(28, "No space left on device", str(tmp))

    with pytest.raises(OSError):
        replace_file(path, broken)
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_check_folder_target_rules(tmp_path):
    assert check_folder_target(tmp_path / "new", ("poses.jsonl",)) is False
    (tmp_path / "res").mkdir()
    (tmp_path / "res" / "notes.txt").write_text("user's")
    assert check_folder_target(tmp_path / "res", ("poses.jsonl",)) is False  # other files are not a result
    (tmp_path / "res" / "poses.jsonl").write_text("")
    with pytest.raises(UserError, match="earlier result"):
        check_folder_target(tmp_path / "res", ("poses.jsonl",))
    assert check_folder_target(tmp_path / "res", ("poses.jsonl",), resume=True) is True


def test_export_and_report_refuse_to_overwrite(fitted, tmp_path, capsys):
    bvh = (fitted / "motion.bvh").read_bytes()  # mocap fit wrote it
    code, err = run(capsys, "export", fitted, "--format", "bvh", "--rest", "tpose")  # other bytes
    assert code == 2
    # no --out given: the default file is named alone, and --out offered
    assert one_error_line(err).endswith(f"error: {fitted / 'motion.bvh'}: exists; pass --overwrite to replace it, "
                                        "or --out to write elsewhere")
    code, err = run(capsys, "export", fitted, "--format", "bvh", "--rest", "tpose", "--out", fitted / "motion.bvh")
    assert code == 2
    assert one_error_line(err).endswith(f"error: --out {fitted / 'motion.bvh'}: exists; pass --overwrite to "
                                        "replace it")
    assert (fitted / "motion.bvh").read_bytes() == bvh
    # the same bytes as the fit's: nothing to lose, so not refused
    assert run(capsys, "export", fitted, "--format", "bvh", "--quiet")[0] == 0
    assert (fitted / "motion.bvh").read_bytes() == bvh
    assert run(capsys, "export", fitted, "--format", "bvh", "--rest", "tpose", "--overwrite", "--quiet")[0] == 0
    assert run(capsys, "report", fitted, "--no-pictures", "--quiet")[0] == 0
    before = (fitted / "report.html").read_bytes()
    code, err = run(capsys, "report", fitted, "--no-pictures", "--quiet")
    assert code == 2
    assert one_error_line(err).endswith(f"error: {fitted / 'report.html'}: exists; pass --overwrite to replace "
                                        "it, or --out to write elsewhere")
    assert (fitted / "report.html").read_bytes() == before


def test_voxels_and_segment_refuse_to_overwrite(tmp_path, seq, capsys):
    out = tmp_path / "vox"
    assert run(capsys, "voxels", seq, "--out", out, "--grid", "16", "--quiet")[0] == 0
    before = snapshot(out)
    code, err = run(capsys, "voxels", seq, "--out", out, "--grid", "16", "--quiet")
    assert code == 2
    one_error_line(err, str(out), "--overwrite")
    assert snapshot(out) == before
    assert run(capsys, "voxels", seq, "--out", out, "--grid", "16", "--quiet", "--overwrite", "--frames", "1")[0] == 0
    assert len(list((out / "voxels").iterdir())) == 1


def test_segment_refuses_existing_silhouettes(tmp_path, capsys):
    seq = tmp_path / "seq"
    assert run(capsys, "synth", "--out", seq, "--cameras", "2", "--frames", "1", "--size", "80x60", "--images",
               "--quiet")[0] == 0
    before = snapshot(seq / "silhouettes")
    code, err = run(capsys, "segment", seq)
    assert code == 2
    one_error_line(err, "silhouettes", "--overwrite")
    assert snapshot(seq / "silhouettes") == before
    code, err = run(capsys, "segment", seq, "--overwrite")
    assert code == 0, err
    assert sorted(snapshot(seq / "silhouettes")) == sorted(before)


def test_the_demo_makes_again_only_a_folder_it_made(tmp_path, capsys):
    """``mocap demo --out DIR`` makes DIR's sequence/ and result/ again on every run: a folder
    holding anything the demo did not make is refused before a file is touched."""
    from server.demo import DEMO_MARK, claim_demo_folder

    take = tmp_path / "take"
    (take / "sequence").mkdir(parents=True)
    (take / "sequence" / "notes.txt").write_text("mine")
    before = snapshot(take)
    code, err = run(capsys, "demo", "--out", take, "--frames", "1")
    assert code == 2
    one_error_line(err, str(take), "did not make")
    assert snapshot(take) == before
    claim_demo_folder(tmp_path / "new")  # a new folder, and again once it is the demo's
    (tmp_path / "new" / "result").mkdir()
    claim_demo_folder(tmp_path / "new")
    assert (tmp_path / "new" / DEMO_MARK).is_file()


@pytest.mark.parametrize("edit, said", [
    (lambda lines: [lines[1], lines[0], *lines[2:]], "out of order or repeated"),
    (lambda lines: [lines[0], *lines], "out of order or repeated"),
    (lambda lines: [re.sub(r'("params": \[)[^,]+', r"\1NaN", lines[0], count=1), *lines[1:]], "finite numbers"),
    (lambda lines: [re.sub(r'("l_knee": \[)[^,]+', r"\1NaN", lines[0], count=1), *lines[1:]],
     "joints: l_knee: expected 3 finite numbers"),
    (lambda lines: [re.sub(r'("pelvis": \[)[^,]+', r'\1"x"', lines[0], count=1), *lines[1:]],
     "joints: pelvis: expected 3 finite numbers"),
])
def test_export_refuses_poses_out_of_order_repeated_or_not_numbers(fitted, tmp_path, capsys, edit, said):
    """Lines swapped or repeated by hand would play backwards or twice; NaN parameters would be
    written as they are."""
    poses = fitted / "poses.jsonl"
    poses.write_text("\n".join(edit(poses.read_text().splitlines())) + "\n")
    code, err = run(capsys, "export", fitted, "--format", "csv", "--out", tmp_path / "m.csv")
    assert code == 2
    one_error_line(err, "poses.jsonl", "line ", said)
    assert not (tmp_path / "m.csv").exists()


def test_export_of_a_torn_or_interrupted_result_says_what_it_left_out(fitted, seq, tmp_path, capsys):
    poses = fitted / "poses.jsonl"
    first, second = poses.read_text().splitlines()[:2]
    poses.write_text(first + "\n" + second[:40])  # a run stopped while writing its second frame
    (fitted / "summary.json").unlink()  # ... before its summary: run.json still names the sequence
    code, err = run(capsys, "export", fitted, "--format", "csv", "--out", tmp_path / "m.csv")
    assert code == 0, err
    assert "warning:" in err and "line 2 is incomplete" in err
    assert len((tmp_path / "m.csv").read_text().splitlines()) == 2  # the header and one frame
    shutil.rmtree(seq)
    code, err = run(capsys, "export", fitted, "--format", "csv", "--out", tmp_path / "m2.csv")
    assert code == 2
    one_error_line(err, str(seq.resolve()), "--fps")


def test_resume_and_overwrite_together_are_refused(fitted, seq, capsys):
    before = snapshot(fitted)
    code, err = run(capsys, "fit", seq, "--out", fitted, "--resume", "--overwrite", *FAST)
    assert code == 2
    one_error_line(err, "--resume", "--overwrite", "one of them")
    assert snapshot(fitted) == before


@pytest.mark.parametrize("argv, said", [
    (["fit", "SEQ", "--out", "R", "--bogus", "1"], "mocap fit: error: unrecognized arguments: --bogus 1 "
                                                     "(see mocap fit --help)"),
    (["calib", "convert", "a", "b", "--nope"], "mocap calib convert: error: unrecognized arguments: --nope "
                                               "(see mocap calib convert --help)"),
])
def test_an_unknown_option_is_named_by_its_command(capsys, argv, said):
    code, err = run(capsys, *argv)
    assert code == 2 and err.strip() == said


def test_synth_says_when_the_clip_holds_fewer_frames_than_asked(tmp_path, capsys):
    code, err = run(capsys, "synth", "--out", tmp_path / "s", "--frames", "100000", "--step", "100",
                    "--size", "80x60", "--cameras", "3", "--quiet")
    assert code == 0, err
    assert "warning:" in err and "synthesising 6 frames, not 100000" in err
    assert json.loads((tmp_path / "s" / "sequence.json").read_text())["frames"] == [0, 1, 2, 3, 4, 5]
    code, err = run(capsys, "synth", "--out", tmp_path / "s2", "--start", "99999", "--quiet")
    assert code == 2
    one_error_line(err, "--start 99999", "last frame")
    assert not (tmp_path / "s2").exists()


@pytest.mark.parametrize("fmt, name, said", [
    ("bvh", "y.glb", "names a .glb file, and a bvh export is a .bvh file"),
    ("keypoints3d", "k.json", "names a .json file, and a keypoints3d export is a folder of one JSON file per frame"),
])
def test_export_refuses_a_name_that_says_another_format(fitted, tmp_path, capsys, fmt, name, said):
    code, err = run(capsys, "export", fitted, "--format", fmt, "--out", tmp_path / name)
    assert code == 2
    one_error_line(err, f"--out {tmp_path / name}", said)
    assert not (tmp_path / name).exists()
    code, err = run(capsys, "export", fitted, "--format", "json", "--out", tmp_path / "m.json")  # its own, by another name
    assert code == 0, err


def test_export_keeps_a_users_files_in_the_keypoints_folder_it_would_replace(fitted, tmp_path, capsys):
    folder = tmp_path / "kp"
    folder.mkdir()
    (folder / "mine.txt").write_text("notes")
    code, err = run(capsys, "export", fitted, "--format", "keypoints3d", "--out", folder, "--overwrite")
    assert code == 2
    one_error_line(err, str(folder), "holds files that are no keypoints3d export (mine.txt)")
    assert (folder / "mine.txt").read_text() == "notes"
    (folder / "mine.txt").unlink()
    assert run(capsys, "export", fitted, "--format", "keypoints3d", "--out", folder)[0] == 0
    assert run(capsys, "export", fitted, "--format", "keypoints3d", "--out", folder, "--overwrite")[0] == 0


def test_export_says_which_frames_are_missing_from_the_step(fitted, tmp_path, capsys):
    """A frame missing between fitted ones (0, 1, 3): the formats of one fixed rate play the
    frames after it early, which the export says; its error lines list the frames without it."""
    poses = fitted / "poses.jsonl"
    lines = poses.read_text().splitlines()
    third = json.loads(lines[1]) | {"frame": 3}
    poses.write_text("\n".join([*lines, json.dumps(third)]) + "\n")
    code, err = run(capsys, "export", fitted, "--format", "bvh", "--out", tmp_path / "m.bvh")
    assert code == 0, err
    assert "frame 2 of the fitted frames' step is missing: bvh (one fixed rate) play" in err
    code, err = run(capsys, "export", fitted, "--format", "csv", "--out", tmp_path / "m.csv")
    assert code == 0 and "missing" not in err  # each frame keeps its time
    code, err = run(capsys, "report", fitted, "--frames", "2", "--no-pictures")
    assert code == 2 and "(frames fitted: 0..3, without 2)" in err


def test_a_damaged_summary_is_read_around(fitted, tmp_path, capsys):
    """summary.json is written last and only describes the run: a damaged one is said, and the
    exports are made from poses.jsonl, the sequence named by run.json."""
    (fitted / "summary.json").write_text("{not json")
    code, err = run(capsys, "export", fitted, "--format", "bvh", "--out", tmp_path / "m.bvh")
    assert code == 0, err
    assert f"warning: {fitted / 'summary.json'}: not valid JSON" in err and (tmp_path / "m.bvh").is_file()
