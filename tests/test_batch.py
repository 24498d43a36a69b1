"""A project of takes: Config.toml cascade, ``mocap run`` (steps skipped when up to date) and
``mocap batch`` on a real local Dask cluster of 2 worker processes (those two tests are slow:
``make batch-test``, which CI runs)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from common.errors import InputFileError, UserError
from common.export import FORMATS
from server.cli import main
from server.config import load_config
from server.project import plan_take, run_take
from server.takes import find_takes

pytestmark = pytest.mark.timeout(300)

PROJECT_CONFIG = """
[fit]
iterations = 1
refine_passes = 0
turn_hypotheses = 0
polish_iterations = 0

[report]
gif = false
"""
# a number for the actor's height, as mocap fit --actor-height takes it (and no size search); a quick fit
# (one frame from a standing start: the fits here are only run or not), no report
QUICK_CONFIG = (PROJECT_CONFIG.replace("[fit]", "[fit]\nactor_height = 1.66\nframes = 1\ninit = 'standing'")
                .replace("[report]", "[report]\nenabled = false"))


def make_take(folder: Path, model, studio, frames: int = 3, start: int = 1) -> Path:
    from common.synth import SynthOptions, synthesize

    from tests.conftest import WALK_CLIP

    synthesize(model, studio, WALK_CLIP, folder, SynthOptions(frames=frames, start=start, step=4, seed=0))
    return folder


def make_image_take(folder: Path, model, studio, frames: int = 2) -> Path:
    """A take of colour image folders and empty-studio backgrounds (imported, then segmented)."""
    from common.synth import SynthOptions, synthesize

    from tests.conftest import WALK_CLIP

    rendered = folder.parent / f".{folder.name}.rendered"
    synthesize(model, studio, WALK_CLIP, rendered, SynthOptions(frames=frames, images=True, seed=0))
    folder.mkdir(parents=True)
    for name in ("images", "background", "calibration.json"):
        shutil.move(rendered / name, folder / name)
    shutil.rmtree(rendered)
    return folder


def hand_fit(take: Path, frames: int = 1) -> int:
    """mocap fit by hand into the take's result folder, as a user would."""
    return main(["fit", str(take), "--out", str(take / "result"), "--frames", str(frames), "--iterations", "1",
                 "--refine-passes", "0", "--turn-hypotheses", "0", "--polish-iterations", "0", "--quiet"])


def refusal(capsys) -> str:
    """The one error line of a refused mocap command."""
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.fixture
def project(tmp_path, model, small_studio) -> Path:
    """3 takes: two good ones (walk from two starts), one with a silhouette file missing."""
    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(PROJECT_CONFIG)
    make_take(root / "walk_a", model, small_studio)
    make_take(root / "walk_b", model, small_studio, start=20)
    make_take(root / "broken", model, small_studio)
    (root / "broken" / "silhouettes" / "cam2" / "000001.png").unlink()
    return root


def poses(take: Path) -> list:
    return [json.loads(line)["params"] for line in (take / "result" / "poses.jsonl").read_text().splitlines()]


def test_config_cascade_and_sources(tmp_path):
    (tmp_path / "take").mkdir()
    (tmp_path / "Config.toml").write_text("[fit]\niterations = 2\nrefine_passes = 0\n")
    (tmp_path / "take" / "Config.toml").write_text("[fit]\niterations = 3\n[export]\nformats = ['csv']\n")
    config = load_config([tmp_path / "Config.toml", tmp_path / "take" / "Config.toml"])
    assert config.get("fit", "iterations") == 3 and config.source("fit", "iterations").endswith("take/Config.toml")
    assert config.get("fit", "refine_passes") == 0 and config.source("fit", "refine_passes") == str(
        tmp_path / "Config.toml")
    assert config.source("fit", "energy") == "default"
    assert config.get("export", "formats") == ["csv"]


def test_the_search_s_knobs_reach_mocap_run_s_fit_only_where_set(tmp_path):
    """[fit] keys with no mocap fit option of their own go to the fit as --set, and the mask
    threshold as --mask-threshold, where a Config.toml sets them away from their defaults; at
    their defaults they are in neither the command nor the step's record, so takes fitted
    before the keys existed are not fitted again."""
    take = tmp_path / "take"
    (take / "silhouettes").mkdir(parents=True)
    (take / "calibration.json").write_text("{}")  # a ready sequence's own: planning reads no file
    (tmp_path / "Config.toml").write_text("[fit]\niterations = 2\n")

    def fit_step():
        (step,) = [s for s in plan_take(take).steps if s.name == "fit"]
        return step, step.commands[0]

    step, command = fit_step()
    assert "--set" not in command and "--mask-threshold" not in command
    assert not {"grid_steps", "redetect", "mask_threshold"} & set(step.settings["fit"])
    (take / "Config.toml").write_text("[fit]\ngrid_steps = 5\nredetect = false\nturn_step = 0.2\nmask_threshold = 127\n")
    step, command = fit_step()
    sets = [command[i + 1] for i, a in enumerate(command) if a == "--set"]
    assert sets == ["fit.grid_steps=5", "fit.turn_step=0.2", "fit.redetect=false"]
    assert command[command.index("--mask-threshold") + 1] == "127"
    assert step.settings["fit"]["grid_steps"] == 5 and step.settings["fit"]["mask_threshold"] == 127
    # the schedules: a take's file replaces those it names, over the project's
    (tmp_path / "Config.toml").write_text('[fit.schedules.tracking]\nstages = [{proposers = ["start"]}]\n')
    (take / "Config.toml").write_text("[fit.schedules]\nsearch_hops = 5\n")
    step, command = fit_step()
    sets = [command[i + 1] for i, a in enumerate(command) if a == "--set"]
    assert sets == ['fit.schedules={tracking = {stages = [{proposers = ["start"]}]}, search_hops = 5}']
    assert step.settings["fit"]["schedules"] == {"tracking": {"stages": [{"proposers": ["start"]}]}, "search_hops": 5}
    shown = "\n".join(load_config([tmp_path / "Config.toml", take / "Config.toml"]).lines())
    assert ('[fit.schedules] tracking = {stages = [{proposers = ["start"]}], budget = 0}   # '
            f'{tmp_path / "Config.toml"}\n') in shown
    assert f"[fit.schedules] search_hops = 5   # {take / 'Config.toml'}" in shown
    assert "[fit.schedules] refine = {stages = [" in shown and shown.count("# default") > 5


@pytest.mark.parametrize("text, names", [
    ("[fit]\niteration = 2\n", ["[fit] unknown key 'iteration' (did you mean 'iterations'?)"]),
    ("[fitting]\niterations = 2\n", ["unknown section [fitting]"]),
    ("[fit]\niterations = 'two'\n", ["[fit] iterations", "an integer"]),
    ("[fit]\niterations = 0\n", ["[fit] iterations", ">= 1"]),
    ("[export]\nformats = ['gif']\n", ["[export] formats"]),
    ("[fit\n", ["not valid TOML"]),
    ("[fit]\nactor_height = 3.5\n", ["[fit] actor_height", "0.5 to 3", "3.5"]),
    ("[fit]\nactor_height = 'tall'\n", ["[fit] actor_height", "metres", "auto"]),
    ("[fit]\niterations = true\n", ["[fit] iterations: expected an integer >= 1, got true"]),
])
def test_bad_config_is_one_line_naming_file_and_key(tmp_path, capsys, text, names):
    take = tmp_path / "take"
    (take / "silhouettes").mkdir(parents=True)
    (tmp_path / "Config.toml").write_text(text)
    assert main(["config", "show", str(take)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    for name in [str(tmp_path / "Config.toml"), *names]:
        assert name in err, err


def test_config_show_says_where_each_value_came_from(project, capsys):
    (project / "walk_a" / "Config.toml").write_text("[fit]\nframes = 2\n")
    assert main(["config", "show", str(project / "walk_a")]) == 0
    out = capsys.readouterr().out
    assert f"[fit] frames = 2   # {project / 'walk_a' / 'Config.toml'}" in out
    assert f"[fit] iterations = 1   # {project / 'Config.toml'}" in out
    assert '[fit] energy = "cpu"   # default' in out


@pytest.mark.timeout(30)
def test_config_keys_prints_a_config_toml_of_the_defaults(tmp_path, capsys):
    """Pasted whole or a line at a time, what mocap config keys prints is TOML a Config.toml may
    hold: every key at its default, those a preset sets commented out (uncommented, the same),
    so that the file saved with another preset takes the preset's values."""
    import tomllib

    from server.config import PRESET_KEYS, PRESETS, SCHEDULES_KEY, SETTINGS, read_config_file

    assert main(["config", "keys"]) == 0
    out = capsys.readouterr().out
    for line in out.splitlines():
        tomllib.loads(line)  # raises on a line that is not TOML
        if " = " in line:
            tomllib.loads(line.removeprefix("# "))
    (tmp_path / "Config.toml").write_text(out)
    defaults = {(s.section, s.key): s.default for s in SETTINGS}
    commented = PRESET_KEYS | {SCHEDULES_KEY}  # the schedules commented out too: [fit.schedules.NAME] tables set them
    assert read_config_file(tmp_path / "Config.toml") == {k: v for k, v in defaults.items() if k not in commented}
    with_tables = out + '\n[fit.schedules.tracking]\nstages = [{proposers = ["start"]}]\n'
    (tmp_path / "Config.toml").write_text(with_tables)  # a schedule's table added to the file as printed
    tracking = {"tracking": {"stages": [{"proposers": ["start"]}]}}
    assert read_config_file(tmp_path / "Config.toml")[SCHEDULES_KEY] == tracking
    uncommented = "\n".join(line.removeprefix("# ") if " = " in line else line for line in out.splitlines())
    (tmp_path / "Config.toml").write_text(uncommented)
    assert read_config_file(tmp_path / "Config.toml") == defaults
    (tmp_path / "take").mkdir()
    (tmp_path / "take" / "Config.toml").write_text(out.replace('preset = "default"', 'preset = "best"'))
    assert load_config([tmp_path / "take" / "Config.toml"]).section("fit").items() >= PRESETS["best"].items()


@pytest.mark.timeout(30)
@pytest.mark.parametrize("value", [True, 0.5, 3, "a\\b 'c' \"d\"\n\x7f\u00e9", ["bvh", "trc"], {"cam 2": 3, "cam1": -1},
                                   {}])
def test_config_values_are_shown_as_toml(value):
    import tomllib

    from server.config import toml_value

    assert tomllib.loads(f"key = {toml_value(value)}")["key"] == value


@pytest.mark.timeout(30)
def test_config_show_takes_one_file_and_refuses_what_is_not_there(tmp_path, capsys):
    """A Config.toml given alone is shown over the defaults, as mocap fit --config reads it; a
    missing path is refused (a typo must not show the defaults as if they were a take's)."""
    (tmp_path / "Config.toml").write_text("[fit]\niterations = 2\npreset = 'fast'\n")
    assert main(["config", "show", str(tmp_path / "Config.toml")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{tmp_path / 'Config.toml'}: over the defaults")
    assert f"[fit] iterations = 2   # {tmp_path / 'Config.toml'}" in out and "# preset fast" in out
    assert main(["config", "show", str(tmp_path / "missing")]) == 2
    assert refusal(capsys).endswith(f"{tmp_path / 'missing'}: no such folder or file")


def test_run_redoes_only_what_changed(project, capsys):
    take = project / "walk_a"
    first = run_take(take)
    assert [s["status"] for s in first["steps"]] == ["done"] * 3  # fit, export, report
    assert (take / "result" / "motion.trc").is_file() and (take / "result" / "report.html").is_file()
    fitted = (take / "result" / "poses.jsonl").stat().st_mtime_ns
    assert first["actor_scale"] == 1.0 and 0 <= first["mean_outside_share"] <= first["mean_xor_share"] < 0.3
    assert first["mean_xor_share"] == pytest.approx(first["mean_outside_share"] + first["mean_missed_share"], abs=1e-3)
    assert first["frames_flagged"] == 0
    again = run_take(take)
    assert again["status"] == "skipped" and {s["status"] for s in again["steps"]} == {"up to date"}
    capsys.readouterr()
    assert main(["run", str(take)]) == 0  # what a take is checked by, also when nothing ran
    said = capsys.readouterr().out
    assert "actor size 1.00 x the body model" in said and "masks the body misses" in said
    assert "0 frames flagged (report.html)" in said
    (take / "Config.toml").write_text("[export]\nformats = ['csv', 'json']\n")
    changed = run_take(take)
    assert [s["status"] for s in changed["steps"]] == ["up to date", "done", "up to date"]
    assert (take / "result" / "motion.jsonl").is_file()
    assert (take / "result" / "poses.jsonl").stat().st_mtime_ns == fitted
    # exported again by hand to the same bytes: still the run's own export, replaced by a refit
    assert main(["export", str(take / "result"), "--format", "csv", "--quiet"]) == 0
    (take / "Config.toml").write_text("[fit]\nframes = 2\n")
    refit = run_take(take)
    assert [s["status"] for s in refit["steps"]] == ["done"] * 3
    assert len(poses(take)) == 2


def test_a_ready_sequence_without_a_calibration_takes_the_projects(tmp_path, model, small_studio, capsys):
    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(QUICK_CONFIG)
    take = make_take(root / "nocal", model, small_studio, frames=1)
    (take / "calibration.json").rename(root / "calibration.json")
    fit = next(s for s in plan_take(take).steps if s.name == "fit")
    assert root / "calibration.json" in fit.inputs
    assert fit.commands[0][fit.commands[0].index("--calibration") + 1] == str(root / "calibration.json")
    assert run_take(take)["status"] == "done"
    assert json.loads((take / "result" / "run.json").read_text())["calibration"] == str(root / "calibration.json")
    # the result's readers read the sequence with it again
    assert main(["export", str(take / "result"), "--format", "c3d", "--quiet"]) == 0
    # its own calibration, where it has one, is the one used
    shutil.copy(root / "calibration.json", take / "calibration.json")
    fit = next(s for s in plan_take(take).steps if s.name == "fit")
    assert "--calibration" not in fit.commands[0] and take / "calibration.json" in fit.inputs
    # neither: one line naming where it looked
    (take / "calibration.json").unlink()
    (root / "calibration.json").unlink()
    capsys.readouterr()
    assert main(["run", str(take)]) == 2
    assert "no calibration" in refusal(capsys)
    assert main(["run", str(take), "--json"]) == 2  # a script reading stdout gets JSON either way
    said = json.loads(capsys.readouterr().out)
    assert said["status"] == "failed" and "no calibration" in said["error"]


def test_all_export_formats_in_a_config(project):
    take = project / "walk_a"
    (take / "Config.toml").write_text("[export]\nformats = ['all']\n")
    (export,) = [s for s in plan_take(take).steps if s.name == "export"]
    assert [c[c.index("--format") + 1] for c in export.commands] == list(FORMATS)


def test_a_takes_fit_settings_reach_its_fit_command(project):
    take = project / "walk_a"
    (fit,) = plan_take(take).steps[0].commands
    assert "--track-moved-on" not in fit and fit[fit.index("--turn-hypotheses") + 1] == "0"
    (take / "Config.toml").write_text("[fit]\ntrack_moved_on = true\nturn_hypotheses = 1\n")
    (fit,) = plan_take(take).steps[0].commands
    assert "--track-moved-on" in fit and fit[fit.index("--turn-hypotheses") + 1] == "1"
    assert fit[fit.index("--actor-height") + 1] == "auto"
    for height in ("1.8", "'1.8'"):  # metres as a number, as mocap fit --actor-height takes them, or as text
        (take / "Config.toml").write_text(f"[fit]\nactor_height = {height}\n")
        (fit,) = plan_take(take).steps[0].commands
        assert fit[fit.index("--actor-height") + 1] == "1.8"


def test_an_interrupted_fit_is_continued(project):
    from server.project import fingerprint

    take = project / "walk_a"
    run_take(take)
    whole = poses(take)
    fit = plan_take(take).steps[0]
    lines = (take / "result" / "poses.jsonl").read_text().splitlines(keepends=True)
    # what a run killed while writing frame 1 leaves: a torn line, a pending record, no done record
    (take / "result" / "poses.jsonl").write_text(lines[0] + lines[1][:30])
    (take / ".mocap" / "fit.json").unlink()
    (take / ".mocap" / "fit.pending.json").write_text(json.dumps(
        {"settings": fit.settings, "inputs": fingerprint(list(fit.inputs))}))
    done = run_take(take)
    assert poses(take) == whole
    summary = json.loads((take / "result" / "summary.json").read_text())
    assert summary["frames_fitted_this_run"] == len(whole) - 1 and done["status"] == "done"
    # an export stopped half way: the files it was replacing are the run's own, not refused
    (take / ".mocap" / "export.json").unlink()
    (take / ".mocap" / "export.pending.json").write_text("{}")
    (take / "result" / "motion.csv").write_text("half written")
    assert [s["status"] for s in run_take(take)["steps"]] == ["up to date", "done", "up to date"]
    assert (take / "result" / "motion.csv").read_text() != "half written"


def test_ctrl_c_in_a_steps_command_stops_the_run_as_ctrl_c(project, monkeypatch, capsys):
    """The fit command catches Ctrl-C and says how it goes on; mocap run stops as interrupted
    (130, not a failed step) and says that running it again goes on, which it does."""
    import server.session as session

    take = project / "walk_a"
    fit_whole = session.run_fit

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(session, "run_fit", interrupted)
    monkeypatch.setattr("server.commands.fit.run_fit", interrupted)
    assert main(["run", str(take)]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "mocap run: interrupted; what was done is kept, and the same command again goes on from there"
    monkeypatch.setattr(session, "run_fit", fit_whole)
    monkeypatch.setattr("server.commands.fit.run_fit", fit_whole)
    assert main(["run", str(take)]) == 0 and len(poses(take)) == 3


def test_run_refuses_a_result_it_did_not_make(project, capsys):
    take = project / "walk_a"
    assert hand_fit(take) == 0
    (take / "result" / "notes.txt").write_text("a user's own file")
    by_hand = {p.name: p.read_bytes() for p in (take / "result").iterdir()}
    capsys.readouterr()
    assert main(["run", str(take)]) == 2
    err = refusal(capsys)
    assert f"{take}: fit: result/poses.jsonl holds a result mocap run did not make" in err and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in (take / "result").iterdir()} == by_hand
    assert not any((take / ".mocap").glob("fit*.json"))
    with pytest.raises(UserError, match="fit: result/poses.jsonl"):  # mocap batch reports the take as failed
        run_take(take)
    assert main(["run", str(take), "--overwrite"]) == 0
    assert len(poses(take)) == 3 and (take / "result" / "report.html").is_file()
    assert (take / "result" / "notes.txt").read_text() == "a user's own file"
    assert {s["status"] for s in run_take(take)["steps"]} == {"up to date"}
    # an export of its own in a format the take's config does not ask for: a refit would drop it
    assert main(["export", str(take / "result"), "--format", "json", "--quiet"]) == 0
    exported = (take / "result" / "motion.jsonl").read_bytes()
    (take / "Config.toml").write_text("[fit]\nframes = 2\n")
    capsys.readouterr()
    assert main(["run", str(take)]) == 2
    assert "fit: result/motion.jsonl holds a result" in refusal(capsys)
    assert (take / "result" / "motion.jsonl").read_bytes() == exported and len(poses(take)) == 3


def test_run_refuses_outputs_changed_since_it_made_them(project, capsys):
    take = project / "walk_a"
    run_take(take)
    csv = take / "result" / "motion.csv"
    csv.write_text(csv.read_text() + "# checked by hand\n")
    edited = csv.read_bytes()
    (take / "Config.toml").write_text("[fit]\nframes = 2\n")  # the fit runs again, and would drop motion.csv
    capsys.readouterr()
    assert main(["run", str(take)]) == 2
    assert "fit: result/motion.csv holds a result mocap run did not make (or one changed since)" in refusal(capsys)
    assert csv.read_bytes() == edited and len(poses(take)) == 3
    (take / "Config.toml").unlink()
    # the export's settings and input as when it ran: it is done, and the edit is kept (mocap batch says so too)
    from server.batch import run_take_task, take_line

    kept = run_take_task(str(take))
    assert kept["status"] == "skipped", kept
    assert [s["status"] for s in kept["steps"]] == ["up to date", "kept (edited)", "up to date"]
    assert "export: kept result/motion.csv as edited since mocap run made it" in take_line(kept)
    assert main(["run", str(take)]) == 0 and csv.read_bytes() == edited
    assert f"walk_a: export: kept result/motion.csv as edited since mocap run made it\n" in capsys.readouterr().out
    csv.unlink()  # an output removed: its step runs
    again = run_take(take)["steps"]
    assert [s["status"] for s in again] == ["up to date", "done", "up to date"]
    assert again[1]["why"] == "result/motion.csv is missing"
    assert csv.read_bytes() != edited
    # a take last run before made.json was kept: the step records vouch for their outputs, then and later
    (take / ".mocap" / "made.json").unlink()
    (take / "Config.toml").write_text("[report]\ngif = true\n")
    assert [s["status"] for s in run_take(take)["steps"]] == ["up to date", "up to date", "done"]
    (take / "Config.toml").write_text("[fit]\nframes = 2\n")
    said = []
    refit = run_take(take, lambda step, state: said.append(f"{step}: {state}"))["steps"]
    assert [s["status"] for s in refit] == ["done"] * 3 and len(poses(take)) == 2
    # each step says why it runs: the fit and the report (gif no longer set) their settings, the
    # export its input, the fit's poses
    assert "fit: running (settings changed: [fit] frames 0 -> 2)" in said
    assert [s["why"] for s in refit[1:]] == ["its inputs changed", "settings changed: [report] gif true -> false"]


@pytest.mark.timeout(150)
def test_run_keeps_touched_up_silhouettes_and_refits_with_them(tmp_path, model, small_studio, capsys):
    """As make: a step whose settings and inputs did not change is done, its outputs edited by
    hand kept and used by the steps after it; one that must run is refused where it would
    replace them, unless --overwrite."""
    from PIL import Image

    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(QUICK_CONFIG + "[export]\nformats = ['csv']\n")
    take = make_image_take(root / "take", model, small_studio)
    assert [s["status"] for s in run_take(take)["steps"]] == ["done"] * 4
    masks = take / "sequence" / "silhouettes"
    (take / "Config.toml").write_text("[segmentation]\nmethod = 'bottino'\n")  # outputs as the run left them
    assert [s["status"] for s in run_take(take)["steps"]] == ["up to date"] + ["done"] * 3
    mask = sorted((masks / "cam1").iterdir())[0]
    with Image.open(mask) as im:
        touched_up = im.copy()
    touched_up.putpixel((0, 0), 255)  # by hand
    touched_up.save(mask)
    touched = {p: p.read_bytes() for p in masks.rglob("*.png")}
    fitted = (take / "result" / "poses.jsonl").stat().st_mtime_ns
    capsys.readouterr()
    assert main(["run", str(take), "--json"]) == 0
    done = json.loads(capsys.readouterr().out)
    assert [s["status"] for s in done["steps"]] == ["up to date", "kept (edited)", "done", "done"]
    assert done["steps"][1]["note"] == "kept sequence/silhouettes as edited since mocap run made it"
    assert {p: p.read_bytes() for p in masks.rglob("*.png")} == touched  # kept, and fitted with
    assert (take / "result" / "poses.jsonl").stat().st_mtime_ns != fitted
    fitted = (take / "result" / "poses.jsonl").read_bytes()
    assert main(["run", str(take)]) == 0  # nothing changed since: nothing runs, the edit is said again
    out = capsys.readouterr().out
    assert f"take: segment: kept sequence/silhouettes as edited since mocap run made it\ntake: skipped" in out
    # the segmentation's settings changed: it would replace the touched-up masks
    (take / "Config.toml").write_text("[segmentation]\nmethod = 'cheung'\n")
    assert main(["run", str(take)]) == 2
    assert f"{take}: segment: sequence/silhouettes holds a result" in refusal(capsys)
    (take / "Config.toml").write_text("[segmentation]\nmethod = 'bottino'\n[import]\nfps = 25.0\n")
    # the import would run again too, and drop the silhouettes
    assert main(["run", str(take)]) == 2
    assert "import: sequence/silhouettes holds a result" in refusal(capsys)
    assert {p: p.read_bytes() for p in masks.rglob("*.png")} == touched
    assert (take / "result" / "poses.jsonl").read_bytes() == fitted
    (take / "Config.toml").write_text("[segmentation]\nmethod = 'cheung'\n")
    assert main(["run", str(take), "--overwrite"]) == 0
    assert mask.read_bytes() != touched[mask]
    assert {s["status"] for s in run_take(take)["steps"]} == {"up to date"}
    capsys.readouterr()
    # an export edited by hand, then a new segmentation: the fit after it would drop the export
    csv = take / "result" / "motion.csv"
    csv.write_text(csv.read_text() + "# checked by hand\n")
    (take / "Config.toml").write_text("[segmentation]\nmethod = 'bottino'\n")
    assert main(["run", str(take)]) == 2
    assert "fit: result/motion.csv holds a result" in refusal(capsys)
    csv.unlink()
    # silhouettes removed: the segmentation runs again, as it would with no record
    (take / "Config.toml").write_text("[segmentation]\nmethod = 'cheung'\n")
    shutil.rmtree(masks)
    assert [s["status"] for s in run_take(take)["steps"]] == ["up to date"] + ["done"] * 3
    assert mask.is_file()
    shutil.rmtree(take / ".mocap")  # a sequence no run made (imported and segmented by hand)
    assert main(["run", str(take)]) == 2
    assert "import: sequence/images holds a result" in refusal(capsys)


def test_batch_reports_a_refused_take_and_overwrite_replaces_it(project):
    from server.batch import run_take_task

    take = project / "walk_a"
    assert hand_fit(take) == 0
    refused = run_take_task(str(take))
    assert refused["status"] == "failed" and "fit: result/poses.jsonl holds a result" in refused["error"]
    assert len(poses(take)) == 1
    assert run_take_task(str(take), overwrite=True)["status"] == "done" and len(poses(take)) == 3


def test_a_take_whose_calibration_needs_units_runs_from_its_images(tmp_path, model, small_studio, capsys):
    """[calibration] units reaches the import step too: a calibration in millimetres that does
    not say so is imported, segmented and fitted under mocap run."""
    from common.calibration import load_calibration, studio_to_json
    from common.synth import SynthOptions, synthesize

    from tests.conftest import WALK_CLIP

    synthesize(model, small_studio, WALK_CLIP, tmp_path / "synth", SynthOptions(frames=2, images=True))
    take = tmp_path / "project" / "take"
    for name in ("images", "background"):
        shutil.copytree(tmp_path / "synth" / name, take / name)
    doc = studio_to_json(small_studio)
    del doc["units"]
    for cam in doc["cameras"]:
        cam["t"] = [1000 * v for v in cam["t"]]
    (take / "calibration.json").write_text(json.dumps(doc))
    (take.parent / "Config.toml").write_text(PROJECT_CONFIG)
    assert main(["run", str(take)]) == 2  # refused before the import, saying where the units are set
    assert refusal(capsys).endswith("(in Config.toml: --units is [calibration] units)")
    (take.parent / "Config.toml").write_text(PROJECT_CONFIG.replace("[report]", "[report]\nenabled = false")
                                             + '\n[calibration]\nunits = "mm"\n')
    (imported,) = plan_take(take).steps[0].commands
    assert imported[0] == "import-video" and imported[imported.index("--units") + 1] == "mm"
    assert "--missing-frames" not in imported
    fit_command = next(s for s in plan_take(take).steps if s.name == "fit").commands[0]
    assert "--units" not in fit_command  # the imported calibration.json is in metres and says so
    done = run_take(take)
    assert [s["step"] for s in done["steps"]] == ["import", "segment", "fit", "export"] and done["frames"] == 2
    studio = load_calibration(take / "sequence" / "calibration.json")
    assert np.allclose([c.t for c in studio], [c.t for c in small_studio])
    (take / "Config.toml").write_text('[import]\nmissing_frames = "skip"\n')
    (imported,) = plan_take(take).steps[0].commands
    assert imported[imported.index("--missing-frames") + 1] == "skip"


def import_images(folder: Path, out: Path, *options: str) -> Path:
    """mocap import-video of a take's image folders and backgrounds into a sequence, as a user would."""
    cameras = sorted(p.name for p in (folder / "images").iterdir())
    assert main(["import-video", "--calibration", str(folder / "calibration.json"), "--out", str(out),
                 "--video", *[f"{c}={folder / 'images' / c}" for c in cameras],
                 "--background", *[f"{c}={folder / 'background' / c}" for c in cameras], *options]) == 0
    return out


@pytest.mark.timeout(150)
def test_a_take_that_is_an_imported_sequence_is_fitted_as_it_is(tmp_path, model, small_studio):
    """A folder mocap import-video made (sequence.json, images/) is a ready sequence: not imported
    again at a guessed frame rate, segmented where it has no silhouettes, fitted at its own rate."""
    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(QUICK_CONFIG)
    recorded = make_image_take(tmp_path / "recorded", model, small_studio)
    seq = import_images(recorded, root / "seq", "--fps", "50")
    assert [s.name for s in plan_take(seq).steps] == ["segment", "fit", "export"]
    done = run_take(seq)
    assert [(s["step"], s["status"]) for s in done["steps"]] == [("segment", "done"), ("fit", "done"),
                                                                 ("export", "done")]
    assert not (seq / "sequence").exists() and json.loads((seq / "sequence.json").read_text())["fps"] == 50
    assert "Frame Time: 0.02\n" in (seq / "result" / "motion.bvh").read_text()
    assert {s["status"] for s in run_take(seq)["steps"]} == {"up to date"}
    (seq / "Config.toml").write_text("[segmentation]\nmethod = 'bottino'\n")  # silhouettes a run made: made again
    assert [s["status"] for s in run_take(seq)["steps"]] == ["done"] * 3
    # segmented by hand: its silhouettes are fitted as they are
    seq = import_images(recorded, root / "segmented", "--fps", "50")
    assert main(["segment", str(seq)]) == 0
    silhouettes = {p: p.read_bytes() for p in (seq / "silhouettes").rglob("*.png")}
    assert [s.name for s in plan_take(seq).steps] == ["fit", "export"]
    assert [s["step"] for s in run_take(seq)["steps"]] == ["fit", "export"]
    assert {p: p.read_bytes() for p in (seq / "silhouettes").rglob("*.png")} == silhouettes
    assert "Frame Time: 0.02\n" in (seq / "result" / "motion.bvh").read_text()


@pytest.mark.timeout(150)
def test_a_take_laid_out_a_folder_per_camera_runs_as_it_is(tmp_path, model, small_studio, capsys):
    """A lab's own layout (the real seated take's: cam1/video.avi, cam1/background.avi,
    cam1/config.xml, a board description at the top) is a take: imported from each camera's
    folder with the take read as its calibration, the board passed over; the outputs written
    into the take do not make its import run again."""
    from common.calibration import save_calibration

    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(QUICK_CONFIG)
    recorded = make_image_take(tmp_path / "recorded", model, small_studio)
    take = root / "lab_take"
    save_calibration(small_studio, tmp_path / "xml", fmt="opencv-xml")
    for cam in small_studio.names:
        shutil.copytree(recorded / "images" / cam, take / cam / "video")
        shutil.copytree(recorded / "background" / cam, take / cam / "background")
        shutil.copy(tmp_path / "xml" / f"{cam}.xml", take / cam / "config.xml")
    (take / "checkerboard.xml").write_text('<?xml version="1.0"?>\n<opencv_storage><CheckerBoardWidth>8'
                                           '</CheckerBoardWidth></opencv_storage>\n')
    assert find_takes(root) == [take]
    plan = plan_take(take)
    (imported,) = plan.steps[0].commands
    assert imported[imported.index("--calibration") + 1] == str(take)
    assert f"cam2={take / 'cam2' / 'video'}" in imported and f"cam2={take / 'cam2' / 'background'}" in imported
    assert main(["config", "show", str(take)]) == 0  # what the run will read, said
    shown = capsys.readouterr().out
    assert "take: recordings: a folder per camera (cam1, cam2, cam3, cam4)\n" in shown
    assert (f"take: calibration: 4 camera files (cam1/config.xml, ..., cam4/config.xml) in {take}\n" in shown)
    done = run_take(take)
    assert [s["step"] for s in done["steps"]] == ["import", "segment", "fit", "export"] and done["frames"] == 1
    assert any("skipped (no camera fields): checkerboard.xml" in w for w in done["steps"][0]["warnings"])
    assert {s["status"] for s in run_take(take)["steps"]} == {"up to date"}
    (take / "cam3" / "config.xml").write_text((take / "cam3" / "config.xml").read_text() + "\n")  # recalibrated
    assert [s["status"] for s in run_take(take)["steps"]] == ["done"] * 4
    shutil.copy(take / "cam3" / "background" / sorted(os.listdir(take / "cam3" / "background"))[0],
                take / "cam3" / "background.png")
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"{take / 'cam3'}: holds 2 background recordings: background, background.png; "
                                    "keep one")
    (take / "cam3" / "background.png").unlink()
    (take / "cam3" / "background").rename(take / "cam3" / "empty")  # named as the lab named it
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"{take}: no background.<ext> for camera(s) cam3 of {take} "
                                    "(cam3/ holds config.xml, empty, video)")
    for cam in ("cam1", "cam2"):  # too few empty-studio recordings to be a take: the folders named
        (take / cam / "background").rename(take / cam / "empty")
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith("; cam1/, cam2/, cam3/ hold video.<ext> but no background.<ext> (the empty studio)")
    for cam in ("cam1", "cam2", "cam3"):
        (take / cam / "empty").rename(take / cam / "background")
    (take / "cam4" / "config.xml").rename(tmp_path / "cam4.xml")
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"{take / 'cam4'}/: no calibration file beside its recording (.xml with K, R, "
                                    "t or P, .txt with a 3x4 P; cameras with one: cam1, cam2, cam3)")
    (tmp_path / "cam4.xml").rename(take / "cam4" / "config.xml")
    save_calibration(small_studio, take / "calibration.json")  # converted beside the cameras' files: which is meant?
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"{take}: holds 2 calibrations: calibration.json, 4 camera files "
                                    "(cam1/config.xml, ..., cam4/config.xml); keep one, or set [calibration] file")
    (take / "calibration.json").unlink()
    for cam in small_studio.names:  # the cameras' files at the take's top, named by camera: read there
        (take / cam / "config.xml").rename(take / f"{cam}.xml")
    assert plan_take(take).calibration == take
    assert main(["config", "show", str(take)]) == 0
    assert f"take: calibration: 4 camera files (cam1.xml, ..., cam4.xml) in {take}\n" in capsys.readouterr().out
    (take / "cam4.xml").rename(take / "camera4.xml")  # named otherwise than its camera's folder
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"{take / 'cam4'}/: no calibration file cam4.xml or .txt at the top of {take} "
                                    "(cameras there: cam1, cam2, cam3, camera4; name each file as its camera's folder)")
    for cam in small_studio.names:  # moved to a calibration/ folder: that one is read
        (take / (f"{cam}.xml" if cam != "cam4" else "camera4.xml")).unlink()
    save_calibration(small_studio, take / "calibration", fmt="opencv-xml")
    assert plan_take(take).calibration == take / "calibration"
    shutil.rmtree(take / "calibration")  # or a Pose2Sim file of another name at the top
    save_calibration(small_studio, take / "rig.toml", fmt="pose2sim")
    assert plan_take(take).calibration == take / "rig.toml"
    assert [s["status"] for s in run_take(take)["steps"]] == ["done"] * 4


@pytest.mark.timeout(150)
def test_run_says_each_step_s_warnings(tmp_path, model, small_studio, capsys):
    """A step's warnings (here the import's frame rate taken for image folders) are said under
    the step, with the log named; in --json they are a list per step and the output stays JSON;
    mocap batch says them per take."""
    from server.batch import run_take_task, warning_lines

    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(QUICK_CONFIG)
    take = make_image_take(root / "take", model, small_studio)
    for name in ("again", "batched"):
        shutil.copytree(take, root / name)
    guess = "the recordings do not say their frame rate: 30 fps taken"
    capsys.readouterr()
    assert main(["run", str(take)]) == 0
    said = capsys.readouterr()
    assert f"  import: running (not run before)\n  import: warning: {guess}" in said.err
    assert f"  full log: {take / '.mocap' / 'run.log'}\n" in said.out
    assert guess in (take / ".mocap" / "run.log").read_text()
    assert main(["run", str(root / "again"), "--json"]) == 0
    said = capsys.readouterr()
    done = json.loads(said.out)
    assert [w.startswith(guess) for w in done["steps"][0]["warnings"]] == [True] and guess not in said.err
    assert [s["warnings"] for s in done["steps"][1:]] == [[]] * 3
    assert main(["run", str(take)]) == 0  # nothing ran: nothing said again
    said = capsys.readouterr()
    assert "warning" not in said.err + said.out and "full log" not in said.out
    lines = warning_lines(run_take_task(str(root / "batched")))
    assert lines[0].startswith(f"  batched: import: warning: {guess}")
    assert lines[1:] == [f"  batched: full log: {root / 'batched' / '.mocap' / 'run.log'}"]


@pytest.mark.timeout(60)
def test_a_take_missing_recordings_is_refused_naming_its_folders(tmp_path, small_studio, capsys):
    """Recordings that do not match the calibration's cameras are said naming the take's folders,
    not import-video's options (the user of mocap run never typed them), before anything is made."""
    from common.calibration import save_calibration
    from server.batch import run_take_task

    take = tmp_path / "project" / "broken"
    (take / "videos" / "cam1").mkdir(parents=True)
    (take / "videos" / "cam1" / "000000.png").write_bytes(b"")  # never read: refused before the import
    save_calibration(small_studio, take / "calibration.json")
    failed = run_take_task(str(take))
    assert failed["status"] == "failed" and "--video" not in failed["error"]
    assert failed["error"] == (f"{take / 'videos'}/: no recording for camera(s) cam2, cam3, cam4 of "
                               f"{take / 'calibration.json'}")
    assert main(["run", str(take)]) == 2 and "videos/: no recording for camera(s) cam2, cam3, cam4" in refusal(capsys)
    assert not (take / "sequence").exists()
    for cam in ("cam2", "cam3", "cam4"):
        (take / "videos" / cam).mkdir()
    (take / "background" / "cam1").mkdir(parents=True)
    assert run_take_task(str(take))["error"] == (f"{take / 'background'}/: no empty-studio recording for "
                                                 f"camera(s) cam2, cam3, cam4 of {take / 'calibration.json'}")
    (take / "videos" / "cam9").mkdir()
    assert run_take_task(str(take))["error"].startswith(f"{take / 'videos' / 'cam9'}: no camera cam9 in ")


@pytest.mark.timeout(30)
def test_run_says_the_fit_quality_without_brackets_in_brackets(tmp_path, monkeypatch, capsys):
    import server.commands.run as run_command

    done = {"name": "seated", "status": "skipped", "result": str(tmp_path / "result"), "log": "run.log",
            "steps": [{"step": "fit", "status": "up to date", "warnings": []}], "frames": 22, "actor_scale": 1.0,
            "mean_xor_share": 0.40, "mean_outside_share": 0.01, "mean_missed_share": 0.39, "frames_flagged": 0}
    monkeypatch.setattr(run_command, "run_take", lambda *args, **kwargs: done)
    assert main(["run", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"XOR 40% of the silhouettes, 0 frames flagged (mocap report {tmp_path / 'result'})" in out  # no report made
    assert "  of the XOR: body outside the masks 1%, masks the body misses 39% (mostly" in out
    assert not any(line.count("(") > 1 for line in out.splitlines()), out
    done.update(mean_xor_share=0.06, mean_outside_share=0.02, mean_missed_share=0.04, cleared_share=0.37)
    assert main(["run", str(tmp_path)]) == 0  # the shares are of the masks with a chair cleared: said so
    out = capsys.readouterr().out
    assert "XOR 6% of the silhouettes once the 37% no fitted pose explains was cleared, 0 frames flagged" in out
    assert not any(line.count("(") > 1 for line in out.splitlines()), out


@pytest.mark.timeout(30)
def test_batch_names_the_index_page(tmp_path, monkeypatch, capsys):
    import server.commands.batch as batch_command

    record = {"project": str(tmp_path), "scheduler": "local", "workers": 1, "seconds": 1.0, "takes": []}
    monkeypatch.setattr(batch_command, "run_batch", lambda *args, **kwargs: record)
    assert main(["batch", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"written {tmp_path / 'batch.json'}\n" in out and f"written {tmp_path / 'index.html'}" in out


def test_run_on_a_broken_take_is_one_line(project, capsys):
    assert main(["run", str(project / "broken")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(err) == 1 and "cam2" in err[0] and "000001.png" in err[0]


def test_the_batch_table_says_each_take_s_fit_quality():
    """A take without truth is judged by its XOR and the XOR's side of the body outside the
    masks; a failed take, or one fitted before the sides were kept, shows what it has."""
    from server.batch import summary_table

    takes = [{"name": "seated", "status": "done", "frames": 22, "seconds_per_frame": 1.5,
              "mean_xor_share": 0.40, "mean_outside_share": 0.01, "mean_missed_share": 0.39},
             {"name": "old", "status": "skipped", "frames": 5, "mean_xor_share": 0.2},
             {"name": "broken", "status": "failed", "error": "cam2: missing"},
             {"name": "chair", "status": "done", "frames": 22, "mean_xor_share": 0.06, "mean_outside_share": 0.02,
              "cleared_share": 0.37}]
    header, seated, old, broken, chair = summary_table({"takes": takes})
    assert "XOR (outside)" in header and "40% (1%)" in seated and "20%" in old and "(" not in old
    assert "6% (2%), 37% cleared" in chair and "cleared" not in seated
    assert broken.split()[3] == "-" and broken.rstrip().endswith("failed: cam2: missing")


def test_find_takes(project):
    from server.takes import folders_without_takes

    assert [t.name for t in find_takes(project)] == ["broken", "walk_a", "walk_b"]
    with pytest.raises(UserError, match="not a take .*; it holds 3 takes: mocap batch .* runs them all"):
        plan_take(project)
    assert folders_without_takes(project) == []
    (project / "empty").mkdir()
    (project / "day2" / "walk_c" / "video").mkdir(parents=True)  # videos/ misspelt
    (project / "day2" / "walk_d").mkdir()
    (project / "day2" / "walk_d" / "sequence.json").write_text("{}")
    (project / "calibration").mkdir()  # the project's calibration folder is no missing take
    assert [p.relative_to(project).as_posix() for p in folders_without_takes(project)] == ["day2/walk_c", "empty"]
    # clips named video.* kept here and there make no take of a folder, nor hide the takes below it
    (project / "day2" / "walk_c" / "video" / "cam1.avi").write_bytes(b"")
    for folder in ("notes", "old"):
        (project / folder).mkdir()
        (project / folder / "video.mp4").write_bytes(b"")
    (project / "walk_a" / "cam1").mkdir()
    (project / "walk_a" / "cam1" / "video.mp4").write_bytes(b"")
    (project / "walk_a" / "cam2").mkdir()
    (project / "walk_a" / "cam2" / "video.json").write_text("{}")
    assert [t.relative_to(project).as_posix() for t in find_takes(project)] == ["broken", "day2/walk_d", "walk_a",
                                                                              "walk_b"]
    assert "day2/walk_c" in [p.relative_to(project).as_posix() for p in folders_without_takes(project)]
    assert folders_without_takes(project / "walk_a") == []


@pytest.mark.timeout(60)
def test_two_calibrations_in_one_folder_of_a_take_are_refused(tmp_path, small_studio, capsys):
    """A take's calibration is looked for by name in the take, then in the project: two in one
    folder are refused naming both; the take's own before the project's is meant."""
    from common.calibration import save_calibration

    root = tmp_path / "project"
    take = root / "take"
    (take / "images" / "cam1").mkdir(parents=True)
    (root / "Config.toml").write_text(PROJECT_CONFIG)
    save_calibration(small_studio, root / "calibration.toml")
    assert plan_take(take).steps[0].commands[0][2] == str(root / "calibration.toml")
    save_calibration(small_studio, take / "calibration.json")
    assert plan_take(take).steps[0].commands[0][2] == str(take / "calibration.json")
    save_calibration(small_studio, take / "Calib.toml")
    with pytest.raises(UserError) as info:
        plan_take(take)
    assert str(info.value) == (f"{take}: holds 2 calibrations: calibration.json, Calib.toml; keep one, "
                               "or set [calibration] file")
    assert main(["run", str(take)]) == 2 and "holds 2 calibrations" in refusal(capsys)
    (take / "Calib.toml").unlink()
    save_calibration(small_studio, take, fmt="easymocap")
    with pytest.raises(UserError, match=r"holds 2 calibrations: calibration.json, intri.yml \+ extri.yml"):
        plan_take(take)
    (take / "calibration.json").unlink()  # EasyMocap's files in the take: they decide the import, not the take
    (imported,) = [step for step in plan_take(take).steps if step.name == "import"]
    assert take / "intri.yml" in imported.inputs and take not in imported.inputs
    (take.parent / "Config.toml").write_text(PROJECT_CONFIG + '\n[calibration]\nfile = "take"\n')  # a folder set
    (imported,) = [step for step in plan_take(take).steps if step.name == "import"]
    assert take / "extri.yml" in imported.inputs and take not in imported.inputs


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_batch_on_a_local_dask_cluster(project, tmp_path, capsys):
    alone = tmp_path / "alone"
    shutil.copytree(project, alone)
    for name in ("walk_a", "walk_b"):
        assert main(["run", str(alone / name)]) == 0
    capsys.readouterr()
    assert main(["batch", str(project), "--workers", "2"]) == 1  # one take failed
    out = capsys.readouterr().out
    record = json.loads((project / "batch.json").read_text())
    by_name = {t["name"]: t for t in record["takes"]}
    assert record["workers"] == 2 and set(by_name) == {"walk_a", "walk_b", "broken"}
    for name in ("walk_a", "walk_b"):
        assert by_name[name]["status"] == "done" and by_name[name]["error"] is None
        assert by_name[name]["result"] == str(project / name / "result")
        assert poses(project / name) == poses(alone / name)
    assert by_name["broken"]["status"] == "failed"
    assert "cam2" in by_name["broken"]["error"] and "\n" not in by_name["broken"]["error"]
    assert "failed" in out and "walk_a" in out and "XOR (outside)" in out
    assert f"  broken: full log: {project / 'broken' / '.mocap' / 'run.log'}\n" in out
    assert f"written {project / 'index.html'}" in out
    assert all(0 <= by_name[n]["mean_outside_share"] <= by_name[n]["mean_xor_share"] for n in ("walk_a", "walk_b"))
    index = (project / "index.html").read_text()
    assert 'href="walk_a/result/report.html"' in index and "body outside them" in index
    before = {n: (project / n / "result" / "poses.jsonl").stat().st_mtime_ns for n in ("walk_a", "walk_b")}
    assert main(["batch", str(project), "--workers", "2", "--quiet"]) == 1
    again = {t["name"]: t["status"] for t in json.loads((project / "batch.json").read_text())["takes"]}
    assert again == {"walk_a": "skipped", "walk_b": "skipped", "broken": "failed"}
    assert before == {n: (project / n / "result" / "poses.jsonl").stat().st_mtime_ns for n in before}


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_a_worker_killed_mid_batch_loses_no_frame(tmp_path, model, small_studio):
    from server.batch import run_batch

    root = tmp_path / "project"
    root.mkdir()
    (root / "Config.toml").write_text(PROJECT_CONFIG.replace("iterations = 1", "iterations = 3"))
    frames = 8
    for name in ("a", "b"):
        make_take(root / name, model, small_studio, frames=frames)
    killed = []

    def kill_one_mid_fit(client) -> None:
        def watch():
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not killed:
                for name in ("a", "b"):
                    path = root / name / "result" / "poses.jsonl"
                    lines = path.read_bytes().count(b"\n") if path.exists() else 0
                    if 1 <= lines < frames - 2:
                        pids = client.run(os.getpid)
                        busy = [w for w, keys in client.processing().items() if any(name in k for k in keys)]
                        if busy and busy[0] in pids:
                            os.kill(pids[busy[0]], signal.SIGKILL)
                            killed.append((name, lines))
                            return
                time.sleep(0.05)

        threading.Thread(target=watch, daemon=True).start()

    record = run_batch(root, workers=2, quiet=True, started=kill_one_mid_fit)
    assert killed, "no worker was killed mid-fit"
    for take in record["takes"]:
        assert take["status"] == "done", take
        records = [json.loads(line) for line in (root / take["name"] / "result" / "poses.jsonl").read_text().splitlines()]
        assert [r["frame"] for r in records] == list(range(frames))  # every frame, once


def test_fit_config_file_sets_defaults_and_flags_win(tmp_path, small_sequence, capsys):
    config = tmp_path / "Config.toml"
    config.write_text('[fit]\niterations = 1\nrefine_passes = 0\nturn_hypotheses = 0\n\n[calibration]\nup = "+z"\n')
    out = tmp_path / "res"
    assert main(["fit", str(small_sequence), "--out", str(out), "--config", str(config), "--quiet", "--frames", "1"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert (run["options"]["max_iterations"], run["options"]["refine_passes"], run["world_up"]) == (1, 0, "+z")
    assert main(["fit", str(small_sequence), "--out", str(out), "--config", str(config), "--quiet", "--frames", "1",
                 "--overwrite", "--iterations", "2"]) == 0
    assert json.loads((out / "run.json").read_text())["options"]["max_iterations"] == 2
    config.write_text("[fit]\niteration = 1\n")
    capsys.readouterr()
    assert main(["fit", str(small_sequence), "--out", str(tmp_path / "other"), "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(config) in err and "unknown key 'iteration'" in err
    # [calibration] file, relative to the Config.toml's folder, read as --calibration would be
    config.write_text('[calibration]\nfile = "lab/none.json"\n')
    assert main(["fit", str(small_sequence), "--out", str(tmp_path / "third"), "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(tmp_path / "lab" / "none.json") in err, err
    (tmp_path / "lab").mkdir()
    shutil.copy(small_sequence / "calibration.json", tmp_path / "lab" / "none.json")
    assert main(["fit", str(small_sequence), "--out", str(tmp_path / "third"), "--config", str(config), "--quiet",
                 "--frames", "1", "--iterations", "1", "--refine-passes", "0"]) == 0


def test_presets_under_the_config_file_under_the_options(tmp_path, small_sequence):
    from server.config import PRESETS

    def options_of(*extra):
        out = tmp_path / f"res{len(list(tmp_path.iterdir()))}"
        assert main(["fit", str(small_sequence), "--out", str(out), "--quiet", "--frames", "1", "--iterations", "1",
                     *extra]) == 0
        return json.loads((out / "run.json").read_text())["options"]

    fast = options_of("--preset", "fast")
    assert {k: fast[k] for k in PRESETS["fast"]} == PRESETS["fast"]
    assert options_of("--preset", "fast", "--refine-passes", "1")["refine_passes"] == 1
    config = tmp_path / "Config.toml"
    config.write_text("[fit]\npolish_iterations = 1\n")
    both = options_of("--preset", "fast", "--config", str(config))
    assert (both["polish_iterations"], both["turn_hypotheses"]) == (1, PRESETS["fast"]["turn_hypotheses"])
    config.write_text('[fit]\npreset = "fast"\npolish_iterations = 1\n')  # the file's preset, under its own keys
    from_file = options_of("--config", str(config))
    assert (from_file["polish_iterations"], from_file["turn_hypotheses"]) == (1, PRESETS["fast"]["turn_hypotheses"])
    assert options_of("--config", str(config), "--preset", "default")["turn_hypotheses"] == 2  # --preset wins


def test_a_projects_preset_under_the_keys_its_files_set(tmp_path):
    """[fit] preset = "best" in the project: its keys in force where no Config.toml sets them,
    each shown as from the preset; a take's own key wins; the name alone is no fit setting of
    the take's plan (a project that names the preset it already spells out refits nothing)."""
    from server.config import PRESETS

    (tmp_path / "take").mkdir()
    (tmp_path / "Config.toml").write_text('[fit]\npreset = "best"\n')
    (tmp_path / "take" / "Config.toml").write_text("[fit]\nrefine_passes = 1\n")
    config = load_config([tmp_path / "Config.toml", tmp_path / "take" / "Config.toml"])
    assert config.get("fit", "refine_hops") == PRESETS["best"]["refine_hops"]
    assert config.get("fit", "refine_search") is True and config.source("fit", "refine_search") == "preset best"
    assert config.get("fit", "refine_passes") == 1 and config.source("fit", "refine_passes").endswith("take/Config.toml")
    assert config.source("fit", "preset") == str(tmp_path / "Config.toml")
    spelled = tmp_path / "spelled"
    spelled.mkdir()
    (spelled / "Config.toml").write_text("[fit]\nrefine_passes = 2\nrefine_search = true\nrefine_hops = 60\n")
    assert load_config([spelled / "Config.toml"]).section("fit") | {"preset": "best"} == config.section("fit") | {
        "refine_passes": 2}
    (tmp_path / "Config.toml").write_text('[fit]\npreset = "quick"\n')
    with pytest.raises(InputFileError, match=r"\[fit\] preset.*one of fast, default, best"):
        load_config([tmp_path / "Config.toml"])


def test_a_preset_named_or_spelled_out_gives_the_same_steps(project):
    """A take whose Config.toml names [fit] preset = "best" and one that spells out the preset's
    keys that no Config.toml sets plan the same steps; the preset's name is in no step's settings, so a project fitted before
    the key existed, or one that names the preset its keys already are, is not fitted again."""
    take = project / "walk_a"
    before = [step.settings for step in plan_take(take).steps]
    assert all("preset" not in step.settings.get("fit", {}) for step in plan_take(take).steps)
    (take / "Config.toml").write_text('[fit]\npreset = "default"\n')
    assert [step.settings for step in plan_take(take).steps] == before
    (take / "Config.toml").write_text('[fit]\npreset = "best"\n')
    named = [step.settings for step in plan_take(take).steps]
    # the project's Config.toml sets refine_passes = 0, which the take's preset does not undo
    (take / "Config.toml").write_text("[fit]\nrefine_search = true\nrefine_hops = 60\n")
    assert [step.settings for step in plan_take(take).steps] == named != before


def test_why_a_step_runs_is_said_from_its_records(project):
    """Each reason a step runs, read from the records a run leaves, and a record of another shape
    (an older version's) never stops the run."""
    from server.project import STATE_DIR, _pending, _record, why_it_runs

    take = project / "walk_a"
    fit, export = (next(s for s in plan_take(take).steps if s.name == name) for name in ("fit", "export"))
    state = take / STATE_DIR
    state.mkdir(exist_ok=True)

    def recorded(step, **changes):
        (state / f"{step.name}.json").write_text(json.dumps(_record(step) | changes))

    assert why_it_runs(take, fit) == "not run before"
    (state / "fit.pending.json").write_text(json.dumps(_pending(fit)))
    assert why_it_runs(take, fit) == "stopped before it finished"
    assert why_it_runs(take, fit, resume=True) == "continued where it stopped"
    was = json.loads(json.dumps(_pending(fit)))  # a copy: the step's own settings stay
    was["settings"]["fit"]["iterations"] = 2
    (state / "fit.pending.json").write_text(json.dumps(was))
    assert why_it_runs(take, fit) == "stopped before it finished; settings changed since: [fit] iterations 2 -> 1"
    (state / "fit.pending.json").write_text(json.dumps(_pending(fit) | {"inputs": "another"}))
    assert why_it_runs(take, fit) == "stopped before it finished; its inputs changed since"
    (state / "fit.pending.json").unlink()
    old = json.loads(json.dumps(_record(fit)))
    old["settings"]["fit"] = dict(old["settings"]["fit"], preset="best", refine_passes=2)
    del old["settings"]["fit"]["threads"]
    recorded(fit, settings=old["settings"])
    assert why_it_runs(take, fit) == ('settings changed: [fit] refine_passes 2 -> 0, [fit] threads (not set) -> 0, '
                                      '[fit] preset "best" -> (not set)')
    recorded(export, settings={"formats": ["bvh"]})
    assert why_it_runs(take, export) == f'settings changed: formats ["bvh"] -> {json.dumps(export.settings["formats"])}'
    recorded(fit, commands=[["fit", "elsewhere"]])
    assert why_it_runs(take, fit) == "its command changed"
    recorded(fit, inputs="another")
    assert why_it_runs(take, fit) == "its inputs changed"
    recorded(fit)
    assert why_it_runs(take, fit) == "result/poses.jsonl is missing"  # the take was never fitted
    for odd in ({"fit": None}, {"fit": [1]}, "a string", None):  # records of other shapes: a reason all the same
        recorded(fit, settings=odd)
        assert why_it_runs(take, fit).startswith(("settings changed", "its record is out of date"))


@pytest.mark.timeout(60)
def test_a_take_without_the_empty_studio_or_with_offsets_of_no_camera_is_refused_before_its_import(tmp_path, small_studio, capsys):
    from common.calibration import save_calibration

    take = tmp_path / "project" / "no_background"
    for cam in ("cam1", "cam2", "cam3", "cam4"):
        (take / "videos" / cam).mkdir(parents=True)
    save_calibration(small_studio, take / "calibration.json")
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"{take / 'background'}/: no empty-studio recording for camera(s) cam1, cam2, "
                                    f"cam3, cam4 of {take / 'calibration.json'}")
    assert not (take / "sequence").exists()
    for cam in ("cam1", "cam2", "cam3", "cam4"):
        (take / "background" / cam).mkdir(parents=True)
    (take / "Config.toml").write_text("[import]\noffsets = { cam5 = 3 }\n")  # as misspelt: said before the import too
    assert main(["run", str(take)]) == 2
    assert refusal(capsys).endswith(f"[import] offsets: no camera cam5 in {take / 'calibration.json'} (cameras: "
                                    "cam1, cam2, cam3, cam4)")
    assert not (take / "sequence").exists()


@pytest.mark.timeout(60)
def test_a_warning_every_step_prints_is_shown_once(project, monkeypatch):
    """Every step that reads a calibration in the wrong units warns of it: mocap run shows the
    line once, and each step's record keeps its own."""
    import server.project as project_module

    def warning_only(command, log, warn):
        warn("calibration.json: the farthest two cameras stand 8195.0 m apart")

    monkeypatch.setattr(project_module, "run_mocap", warning_only)
    shown = []
    done = run_take(project / "walk_a", lambda step, text: shown.append(text))
    said = [t for t in shown if "8195.0 m apart" in t]
    assert len(said) == 1 and all(step["warnings"] for step in done["steps"])


@pytest.mark.timeout(30)
def test_a_steps_error_names_the_config_key_of_the_option_it_names():
    """mocap run's user set the import's and the fit's options in Config.toml, never on a command
    line: an error that says to pass --units also says which key that is."""
    from server.project import config_key_note

    said = "units: camera 'cam1' stands 5929.8 units from the origin; pass --units mm (or cm; --units m)"
    assert config_key_note(said) == " (in Config.toml: --units is [calibration] units)"
    assert config_key_note("--offset cam5: no camera of that name") == " (in Config.toml: --offset is [import] offsets)"
    assert config_key_note("--video cam3: only 3.56 s of the 4.18 s") == ""
    assert config_key_note("--frames-per-second") == ""  # an option only where it is one word
