"""RESULT/report.html: one self-contained page (no network) that shows what a fit did.

The page holds inline CSS and JavaScript and its images as data URIs: the run summary, the
plots, silhouette overlay strips of a few frames (each tile shaped like its camera's image),
the take's overlay video (``pictures/sequence.mp4`` when ``mocap report`` made it, embedded),
3D views of the fitted mesh, per-joint errors, the export commands with the import settings of
Blender, OpenSim, EasyMocap and three.js, and a 3D skeleton player (canvas 2D with its own
perspective projection: play, pause, scrub, orbit by dragging, zoom with the wheel) of the
fitted motion beside the truth where the sequence has one.

Hooks for automated checks: the page records any script error or console.error/warn in the
``data-errors`` / ``data-error-messages`` attributes of <html>; the player counts its draws in
``<body data-frames-drawn>``, the frame shown in ``data-frame`` and its canvas's page rectangle
(CSS pixels) in ``data-canvas-rect``; the take's video, once decoded, its length in
``data-video-duration`` (seconds). ``report.html#frame=N`` opens paused at frame index N
(also ``yaw=DEG``, ``pitch=DEG``, ``play``).

One module of about 570 lines: one HTML page, its sections in the order they appear.
"""
from __future__ import annotations

import base64
import datetime
import html
import json
from pathlib import Path

import numpy as np

from common.body import JOINT_NAMES
from common.export import FORMATS, SUFFIXES, frame_step
from server.output import counted, write_text
from server.pictures import (
    BONES, AGREE, EXTRA, GIF_NAME, MISSED, PICTURES_DIR, VIDEO_NAME, ModelPainter, ResultData, camera_indices,
    default_cameras, default_frames, fit_height, worst_frame, load_result, make_plots, model_views, overlay_strip,
    png_bytes,
)
from server.results import POSES_FILE
from server.session import masks_cleared_note, refinement_note, tracking_error_note, xor_sides

REPORT_NAME = "report.html"
STRIP_HEIGHT = 180     # pixels per camera picture in the overlay strips
VIEW_PANEL = (360, 360)  # pixels per 3D view in the report
MM = 1000.0
VIDEO_EMBED_MAX_BYTES = 32 * 2 ** 20  # a longer take's video is linked rather than embedded
# per export format: what opens it, and with which settings (docs/exports.md says more); {fps}
# is the fitted frames' rate, {up} the user's world's up axis
EXPORT_SETTINGS = {
    "glb": "Blender: File > Import > glTF 2.0 with the defaults (glTF's +Y up becomes Blender's Z up: Blender's world "
           "is then our z-up frame); set the scene to {fps} fps first (Blender keys glTF times at its scene rate). "
           "three.js: GLTFLoader as it is (y up), play gltf.animations[0] with an AnimationMixer.",
    "mot": "OpenSim: File > Load Motion, or opensim.TimeSeriesTable; inDegrees=yes, pelvis_t* in metres in OpenSim's "
           "axes (X forward, Y up, Z right); the angles are this body model's, not an OpenSim model's coordinates.",
    "trc": "OpenSim / Pose2Sim: metres, Y up, X forward; markers named as Pose2Sim's HALPE_26 skeleton (the 15 we "
           "have), for its HALPE_26 scaling and inverse kinematics set-ups; no rotation needed.",
    "keypoints3d": "EasyMocap: one file per frame, body25 order, confidence 0 for the points we do not fit; in the "
                   "calibration's own world (metres), so EasyMocap's SMPL fit can use the same cameras.",
    "bvh": "Blender: File > Import > Motion Capture (.bvh), Forward -Z, Up Y (the defaults), Scale 0.01 for metres, "
           "Update Scene FPS; --rest tpose gives a T-pose rest for retargeting (the motion is the same).",
    "c3d": "Mokka, ezc3d: the calibration's world as it is ({up} up), millimetres.",
    "json": "Any JSON reader: one frame per line, the calibration's world ({up} up), metres.",
    "csv": "Spreadsheets, pandas: the calibration's world ({up} up), metres.",
}


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _esc(value) -> str:
    return html.escape(str(value), quote=True)


def _fmt(value, spec: str = ".3f", unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    return f"{value:{spec}}{unit}"


def _json_for_script(doc) -> str:
    """JSON safe inside <script type="application/json"> (no '</' sequences)."""
    return json.dumps(doc, separators=(",", ":")).replace("</", "<\\/")


def player_data(result: ResultData) -> dict:
    """What the skeleton player needs: joints in mm (rounded), bones, per-frame numbers."""
    m = result.motion
    fitted = np.round(m.fit_joints * MM).astype(int).reshape(len(m.frames), -1).tolist()  # upright: z up
    truth = None
    if result.truth is not None:
        truth = [None if np.any(np.isnan(t)) else np.round(t * MM).astype(int).reshape(-1).tolist()
                 for t in result.truth]
    err = result.joint_errors_mm()
    mean_err = None if err is None else [None if np.all(np.isnan(e)) else round(float(np.nanmean(e)), 1) for e in err]
    return {
        "fps": m.fps, "rate": m.rate, "frames": m.frames.tolist(), "joints": list(JOINT_NAMES),
        "bones": [list(b) for b in BONES],
        "side": [1 if n.startswith("l_") else -1 if n.startswith("r_") else 0 for n in JOINT_NAMES],
        "fitted": fitted, "truth": truth, "error": mean_err,
        "energy": [None if not np.isfinite(e) else int(e) for e in result.energies],
    }



def summary_rows(result: ResultData) -> list[tuple[str, str]]:
    s, m = result.summary, result.motion
    step = frame_step(m.frames)
    rate = f"{m.fps:g} fps" + (f", one frame in {step} fitted: {m.rate:g} fps" if step > 1 else "")
    rows = [("frames", f"{len(m.frames)} ({m.frames[0]}..{m.frames[-1]})"), ("frame rate", rate)]
    if "mode" in s:
        rows.append(("mode", f"{s['mode']} ({counted(s.get('clients', 0), 'client')})"))
    if "energy_backend" in s:
        rows.append(("energy backend", s["energy_backend"]))
    refined = bool(s.get("refinement_passes"))
    rows += [
        ("seconds per frame (median)", _fmt(s.get("seconds_per_frame"), ".3f", " s")),
        ("seconds per frame (mean)", _fmt(s.get("mean_seconds_per_frame"), ".3f", " s")),
        ("wall time", _fmt(s.get("wall_seconds"), ".1f", " s")),
        # a resumed fit's: more than this run's wall time
        *([("take time, with earlier runs' tracking", _fmt(s["take_seconds"], ".1f", " s"))]
          if s.get("take_seconds", s.get("wall_seconds")) != s.get("wall_seconds") else []),
        *([("refinement seconds per frame", _fmt(s.get("refine_seconds_per_frame"), ".3f",
                                                 f" s {refinement_note(s)}"))] if refined else []),
        *([("finish seconds per frame", _fmt(s["finish_seconds_per_frame"], ".3f",
                                             f" s ({counted(s.get('frames_finished', 0), 'frame')} lowered)"))]
          if s.get("finish_seconds_per_frame") else []),
        ("evaluations per frame", _fmt(s.get("evaluations_per_frame"), ".0f")),
        ("mean energy (XOR pixels)", _fmt(float(np.nanmean(result.energies)), ".0f")),
    ]
    quality = s.get("fit_quality") or {}
    quality_rows = []
    if quality:
        flagged = quality["frames_flagged"]
        quality_rows = [("fit quality: XOR / silhouette area", f"mean {quality['mean_xor_share']:.0%}, worst frame "
                                                                f"{quality['max_xor_share']:.0%}"),
                        ("XOR share per camera", ", ".join(f"{c} {v:.0%}" for c, v in
                                                          quality["per_camera_mean_xor_share"].items())),
                        *([("of which", xor_sides(quality))] if "mean_missed_share" in quality else []),
                        *([("masks cleared", masks_cleared_note(s["foreground_left_out"]))]
                          if s.get("foreground_left_out") else []),
                        (f"frames over {quality['flag_share']:.0%} in a camera",
                         f"{len(flagged)} of {len(m.frames)}" + (f" (first: frame {flagged[0]['frame']}, "
                                                                  f"{', '.join(flagged[0]['cameras'])})" if flagged else ""))]
    err = result.joint_errors_mm()
    if err is None:  # without truth, how well the body explains the masks comes first
        rows = rows[:2] + quality_rows + rows[2:]
    else:
        rows += quality_rows
    if err is not None:
        rows += [("mean joint error", _fmt(float(np.nanmean(err)), ".1f", " mm")),
                 ("max joint error", _fmt(float(np.nanmax(err)), ".1f", " mm"))]
        if refined and "tracking_mean_joint_error_mm" in s:
            rows.append(("tracking alone, mean / max joint error", tracking_error_note(s)))
    else:
        rows.append(("joint error", "no truth.jsonl in the sequence"))
    if result.sequence is not None:
        st = result.sequence.studio
        sizes = sorted({f"{w}x{h}" for w, h in st.sizes})
        rows += [("cameras", f"{len(st)} ({', '.join(sizes)})"), ("world up axis", result.motion.up),
                 ("sequence", str(result.sequence.path))]
    else:
        rows.append(("sequence", f"{s.get('sequence', '?')} (not found)"))
    rows.append(("result", str(result.path)))
    return rows


def _table(rows, head=None) -> str:
    out = ["<table>"]
    if head:
        out.append("<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _img(png: bytes, alt: str, cls: str = "") -> str:
    return f'<img class="{cls}" alt="{_esc(alt)}" src="{_data_uri(png)}">'


def _swatch(rgb) -> str:
    return f'<span class="sw" style="background:rgb{tuple(rgb)}"></span>'


def export_table(result: ResultData) -> str:
    """The Exports section: per format its command, its file and how to open it."""
    rows = "".join(
        f"<tr><td><code>mocap export {_esc(result.path)} --format {f}</code></td>"
        f"<td><code>motion{_esc(SUFFIXES[f])}</code></td><td>{_esc(EXPORT_SETTINGS[f].format(fps=f'{result.motion.rate:g}', up=result.motion.up))}"
        f"</td></tr>" for f in FORMATS)
    return (f'<p>Several at once: <code>--format glb,trc,mot</code> or <code>--format all</code>. Axes and units: '
            f'docs/exports.md.</p><table class="exports"><tr><th>command</th><th>writes</th><th>open it with</th></tr>'
            f'{rows}</table>')


def video_html(result: ResultData) -> str:
    """The take's overlay video, embedded when ``mocap report`` made it for this fit (no older
    than poses.jsonl) and it is not too big to carry in the page; else a note."""
    video = result.path / PICTURES_DIR / VIDEO_NAME
    poses = result.path / POSES_FILE
    if not video.exists() or video.stat().st_mtime < poses.stat().st_mtime:
        return '<p class="note">No overlay video of this fit yet (<code>mocap report RESULT</code> without ' \
               '<code>--no-gif</code> makes one).</p>'
    size = video.stat().st_size
    caption = (f"Every fitted frame at {result.motion.rate:g} fps: {PICTURES_DIR}/{VIDEO_NAME}, beside "
               f"{PICTURES_DIR}/{GIF_NAME}")
    if size > VIDEO_EMBED_MAX_BYTES:
        return f'<p><a href="{PICTURES_DIR}/{VIDEO_NAME}">{_esc(caption)}</a> ({size / 2 ** 20:.0f} MB, not embedded)</p>'
    uri = "data:video/mp4;base64," + base64.b64encode(video.read_bytes()).decode("ascii")
    return (f'<figure><video class="take" controls muted loop playsinline preload="auto" src="{uri}"></video>'
            f'<figcaption>{_esc(caption)}</figcaption></figure>')


def build_report(result: ResultData, frames=None, cameras=None) -> str:
    """The report page's HTML text."""
    painter = ModelPainter(result.motion.model)
    frames = list(frames) if frames else default_frames(result)
    plots = make_plots(result)
    plot_html = "\n".join(_img(png, name, "plot") for name, png in plots.items())

    if result.sequence is not None:
        cams = camera_indices(result.sequence.studio, cameras or default_cameras(result.sequence.studio))
        strips = []
        for f in frames:
            strip, xor = overlay_strip(result, painter, f, cams, STRIP_HEIGHT, crop=True)
            strips.append(f'<figure>{_img(png_bytes(strip), f"overlays of frame {f}", "strip")}'
                          f'<figcaption>frame {f}: XOR {sum(xor.values())} px over these cameras</figcaption></figure>')
        overlay_html = (f'<p class="legend">{_swatch(AGREE)} silhouette and model {_swatch(MISSED)} silhouette the '
                        f'model misses {_swatch(EXTRA)} model outside the silhouette {_swatch((15, 15, 15))} model '
                        f'outline. The model is drawn on the masks as recorded (its mesh where OpenGL runs); the '
                        f'fit\'s XOR (the table above, poses.jsonl) counts its ellipsoids on the undistorted masks, '
                        f'so the pixel counts differ.</p>' + "\n".join(strips))
    else:
        overlay_html = '<p class="note">The sequence folder was not found, so there are no overlays ' \
                       '(run <code>mocap report RESULT --sequence SEQ</code>).</p>'
    worst = worst_frame(result)
    view_frames = sorted({frames[0], worst})
    worst_label = " (largest error)" if result.truth is not None else " (highest energy: no truth)"
    views = [f'<figure>{_img(png_bytes(fit_height(model_views(result, painter, f, size=VIEW_PANEL), VIEW_PANEL[1])), f"model at frame {f}", "strip")}'
             f'<figcaption>frame {f}{worst_label if f == worst and len(view_frames) > 1 else ""}'
             f'</figcaption></figure>' for f in view_frames]
    truth_note = " The true skeleton is drawn in green." if result.truth is not None else ""

    err = result.joint_errors_mm()
    if err is not None:
        joint_rows = [(n, f"{np.nanmean(err[:, j]):.1f}", f"{np.nanmax(err[:, j]):.1f}") for j, n in enumerate(JOINT_NAMES)]
        joint_html = _table(joint_rows, ("joint", "mean error (mm)", "max error (mm)"))
    else:
        joint_html = '<p class="note">No ground truth for this sequence.</p>'

    exports = export_table(result)
    generated = datetime.datetime.now().isoformat(timespec="seconds")
    replacements = {
        "__TITLE__": _esc(f"silhouette-mocap: {result.path.name}"),
        "__SUBTITLE__": _esc(f"{result.path} · generated {generated}"),
        "__SUMMARY__": _table(summary_rows(result)),
        "__PLOTS__": plot_html,
        "__OVERLAYS__": overlay_html,
        "__VIEWS__": "\n".join(views),
        "__VIDEO__": video_html(result),
        "__TRUTH_NOTE__": truth_note,
        "__JOINTS__": joint_html,
        "__EXPORTS__": exports,
        "__DATA__": _json_for_script(player_data(result)),
        "__HAS_TRUTH__": "" if result.truth is not None else "hidden",
    }
    page = PAGE
    for key, value in replacements.items():
        page = page.replace(key, value)
    return page


def write_report(result_dir, sequence_dir=None, frames=None, cameras=None, out=None, fps: float | None = None) -> Path:
    """Writes RESULT/report.html (or ``out``) and returns its path.

    sequence_dir: where the fitted sequence is, if not at summary.json's path; frames, cameras:
    what the overlay strips show (default: a few frames, up to 4 cameras); fps: the frame rate
    when the sequence is not available.
    """
    result = load_result(result_dir, sequence_dir, fps)
    path = Path(out) if out else result.path / REPORT_NAME
    write_text(path, build_report(result, frames, cameras))
    return path


PAGE = r"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>__TITLE__</title>
<script>
(function () {
  var errors = [];
  function note(msg) {
    errors.push(String(msg));
    document.documentElement.setAttribute("data-errors", String(errors.length));
    document.documentElement.setAttribute("data-error-messages", errors.join(" | "));
  }
  window.addEventListener("error", function (e) { note(e.message || "script error"); });
  window.addEventListener("unhandledrejection", function (e) { note("unhandled rejection: " + e.reason); });
  var origError = console.error, origWarn = console.warn;
  console.error = function () { note(Array.prototype.join.call(arguments, " ")); origError.apply(console, arguments); };
  console.warn = function () { note("warning: " + Array.prototype.join.call(arguments, " ")); origWarn.apply(console, arguments); };
})();
</script>
<style>
  body { font: 14px/1.4 system-ui, -apple-system, "Segoe UI", sans-serif; margin: 0; color: #222; background: #fafafa; }
  header { background: #263238; color: #fff; padding: 12px 20px; }
  header h1 { margin: 0; font-size: 20px; font-weight: 600; }
  header p { margin: 2px 0 0; font-size: 12px; color: #b0bec5; }
  main { padding: 12px 20px 40px; }
  section { margin: 18px 0; }
  h2 { font-size: 16px; margin: 0 0 8px; border-bottom: 1px solid #ddd; padding-bottom: 4px; }
  .top { display: flex; flex-wrap: wrap; gap: 20px; align-items: flex-start; }
  .player { background: #fff; border: 1px solid #ddd; border-radius: 6px; padding: 8px; }
  #player { display: block; width: 640px; height: 440px; background: #f4f6f8; cursor: grab; touch-action: none; }
  #player:active { cursor: grabbing; }
  .controls { display: flex; align-items: center; gap: 8px; margin-top: 6px; font-size: 13px; }
  .controls input[type=range] { flex: 1; }
  .controls button { width: 64px; }
  .options { font-size: 12px; color: #555; margin-top: 4px; display: flex; gap: 14px; flex-wrap: wrap; }
  table { border-collapse: collapse; background: #fff; font-size: 13px; }
  td, th { border: 1px solid #ddd; padding: 3px 8px; text-align: left; }
  th { background: #eceff1; }
  td:nth-child(n+2) { font-variant-numeric: tabular-nums; }
  .plots { display: flex; flex-wrap: wrap; gap: 10px; }
  img.plot { max-width: 100%; border: 1px solid #ddd; background: #fff; }
  img.strip { max-width: 100%; border: 1px solid #ddd; }
  video.take { max-width: 100%; border: 1px solid #ddd; background: #fff; }
  table.exports td:last-child { max-width: 640px; }
  figure { margin: 0 0 10px; }
  figcaption { font-size: 12px; color: #555; }
  .legend { font-size: 12px; color: #444; }
  .sw { display: inline-block; width: 12px; height: 12px; margin: 0 4px 0 10px; vertical-align: -2px; border: 1px solid #999; }
  .note { color: #666; font-style: italic; }
  code { background: #eceff1; padding: 1px 4px; border-radius: 3px; font-size: 12px; }
  .hidden { display: none; }
</style>
</head>
<body>
<header><h1>__TITLE__</h1><p>__SUBTITLE__</p></header>
<main>
<section class="top">
  <div class="player">
    <canvas id="player" width="640" height="440" aria-label="3D skeleton player"></canvas>
    <div class="controls">
      <button id="play" type="button">Pause</button>
      <input id="scrub" type="range" min="0" max="0" value="0" step="1" aria-label="frame">
      <span id="label"></span>
    </div>
    <div class="options">
      <label class="__HAS_TRUTH__"><input id="truth" type="checkbox" checked> truth</label>
      <label class="__HAS_TRUTH__"><input id="beside" type="checkbox" checked> side by side</label>
      <label><input id="follow" type="checkbox" checked> follow actor</label>
      <label>speed <select id="speed"><option>0.25</option><option>0.5</option><option selected>1</option><option>2</option></select></label>
      <span>drag: orbit · wheel: zoom · space: play/pause · arrows: step</span>
    </div>
  </div>
  <div>
    <h2>Summary</h2>
    __SUMMARY__
  </div>
</section>
<section>
  <h2>Plots</h2>
  <div class="plots">__PLOTS__</div>
</section>
<section>
  <h2>Silhouette overlays</h2>
  __OVERLAYS__
</section>
<section>
  <h2>The take</h2>
  __VIDEO__
</section>
<section>
  <h2>Fitted model</h2>
  <p class="legend">The rigid segment mesh at the fitted pose (left side warm, right side cool).__TRUTH_NOTE__</p>
  __VIEWS__
</section>
<section>
  <h2>Joint errors</h2>
  __JOINTS__
</section>
<section>
  <h2>Exports</h2>
  __EXPORTS__
</section>
</main>
<script type="application/json" id="player-data">__DATA__</script>
<script>
(function () {
  "use strict";
  var D = JSON.parse(document.getElementById("player-data").textContent);
  var F = D.frames.length, J = D.joints.length;
  var canvas = document.getElementById("player"), ctx = canvas.getContext("2d");
  var playBtn = document.getElementById("play"), scrub = document.getElementById("scrub");
  var label = document.getElementById("label");
  var truthBox = document.getElementById("truth"), besideBox = document.getElementById("beside");
  var followBox = document.getElementById("follow"), speedSel = document.getElementById("speed");
  var COLOURS = {
    fitted: {"0": "#e4572e", "1": "#f39c4a", "-1": "#b5301a"},
    truth: {"0": "#2e86ab", "1": "#5fb8dd", "-1": "#1b5a78"}
  };
  var DEG = Math.PI / 180;
  var state = { frame: 0, playing: true, yaw: -70 * DEG, pitch: 12 * DEG, dist: 3.4 };
  var drawn = 0;

  var params = new URLSearchParams(location.hash.replace(/^#/, ""));
  if (params.has("frame")) { state.frame = Math.max(0, Math.min(F - 1, parseInt(params.get("frame"), 10) || 0)); state.playing = false; }
  if (params.has("yaw")) { state.yaw = parseFloat(params.get("yaw")) * DEG; }
  if (params.has("pitch")) { state.pitch = parseFloat(params.get("pitch")) * DEG; }
  if (params.has("play")) { state.playing = true; }

  // the height the camera looks at: middle of the body over the whole motion (metres)
  var zmin = Infinity, zmax = -Infinity, cx = 0, cy = 0;
  for (var f = 0; f < F; f++) {
    for (var j = 0; j < J; j++) {
      var z = D.fitted[f][3 * j + 2] / 1000;
      if (z < zmin) zmin = z;
      if (z > zmax) zmax = z;
    }
    cx += D.fitted[f][0] / 1000 / F; cy += D.fitted[f][1] / 1000 / F;
  }
  var zc = 0.5 * (Math.max(zmin, 0) + zmax);

  scrub.max = String(F - 1);

  function joint(arr, j) { return [arr[3 * j] / 1000, arr[3 * j + 1] / 1000, arr[3 * j + 2] / 1000]; }

  function camera(target) {
    var cp = Math.cos(state.pitch), sp = Math.sin(state.pitch), cyw = Math.cos(state.yaw), syw = Math.sin(state.yaw);
    var w = [cp * cyw, cp * syw, sp];              // from the target towards the eye
    var r = [-syw, cyw, 0];                        // screen right
    var u = [-sp * cyw, -sp * syw, cp];            // screen up = w x r
    var focal = 0.5 * canvas.height / Math.tan(20 * DEG);
    return { t: target, w: w, r: r, u: u, focal: focal };
  }

  function project(cam, p) {
    var d = [p[0] - cam.t[0], p[1] - cam.t[1], p[2] - cam.t[2]];
    var depth = state.dist - (d[0] * cam.w[0] + d[1] * cam.w[1] + d[2] * cam.w[2]);
    var x = d[0] * cam.r[0] + d[1] * cam.r[1];
    var y = d[0] * cam.u[0] + d[1] * cam.u[1] + d[2] * cam.u[2];
    return [canvas.width / 2 + cam.focal * x / depth, canvas.height / 2 - cam.focal * y / depth, depth];
  }

  function shift(p, cam, metres) { return [p[0] + cam.r[0] * metres, p[1] + cam.r[1] * metres, p[2]]; }

  function drawFloor(cam) {
    var step = 0.5, half = 2.5;
    var gx = Math.round(cam.t[0] / step) * step, gy = Math.round(cam.t[1] / step) * step;
    ctx.strokeStyle = "#cfd6dc"; ctx.lineWidth = 1;
    for (var k = -half; k <= half + 1e-9; k += step) {
      var segs = [[[gx + k, gy - half, 0], [gx + k, gy + half, 0]], [[gx - half, gy + k, 0], [gx + half, gy + k, 0]]];
      for (var s = 0; s < 2; s++) {
        var a = project(cam, segs[s][0]), b = project(cam, segs[s][1]);
        if (a[2] < 0.1 || b[2] < 0.1) continue;
        ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
      }
    }
  }

  function skeletonItems(arr, cam, offset, palette, alpha, items) {
    var pts = [];
    for (var j = 0; j < J; j++) pts.push(project(cam, shift(joint(arr, j), cam, offset)));
    for (var b = 0; b < D.bones.length; b++) {
      var i0 = D.bones[b][0], i1 = D.bones[b][1];
      items.push({ kind: "bone", a: pts[i0], b: pts[i1], depth: 0.5 * (pts[i0][2] + pts[i1][2]),
                   colour: palette[String(D.side[i1])], alpha: alpha });
    }
    for (var j2 = 0; j2 < J; j2++) {
      items.push({ kind: "joint", a: pts[j2], depth: pts[j2][2] - 0.01, colour: palette[String(D.side[j2])], alpha: alpha });
    }
  }

  function draw() {
    var f = state.frame;
    var fitted = D.fitted[f];
    var truth = D.truth && truthBox.checked ? D.truth[f] : null;
    var pel = joint(fitted, 0);
    var target = followBox.checked ? [pel[0], pel[1], zc] : [cx, cy, zc];
    var cam = camera(target);
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#f4f6f8"; ctx.fillRect(0, 0, canvas.width, canvas.height);
    drawFloor(cam);
    var items = [], apart = truth && besideBox.checked ? 0.45 : 0;
    skeletonItems(fitted, cam, -apart, COLOURS.fitted, 1.0, items);
    if (truth) skeletonItems(truth, cam, apart, COLOURS.truth, apart ? 1.0 : 0.75, items);
    items.sort(function (p, q) { return q.depth - p.depth; });
    ctx.lineCap = "round";
    for (var i = 0; i < items.length; i++) {
      var it = items[i], scale = cam.focal / Math.max(it.depth, 0.1);
      ctx.globalAlpha = it.alpha;
      ctx.strokeStyle = it.colour; ctx.fillStyle = it.colour;
      if (it.kind === "bone") {
        ctx.lineWidth = Math.max(2, 0.035 * scale);
        ctx.beginPath(); ctx.moveTo(it.a[0], it.a[1]); ctx.lineTo(it.b[0], it.b[1]); ctx.stroke();
      } else {
        ctx.beginPath(); ctx.arc(it.a[0], it.a[1], Math.max(2.5, 0.025 * scale), 0, 2 * Math.PI); ctx.fill();
      }
    }
    ctx.globalAlpha = 1;
    ctx.font = "13px system-ui, sans-serif"; ctx.fillStyle = "#333";
    var text = "frame " + D.frames[f] + "  (" + (f + 1) + "/" + F + ")  t = " + ((D.frames[f] - D.frames[0]) / D.fps).toFixed(2) + " s";
    if (D.energy[f] !== null) text += "  energy " + D.energy[f];
    if (D.error && D.error[f] !== null) text += "  error " + D.error[f].toFixed(1) + " mm";
    ctx.fillText(text, 10, 20);
    ctx.fillStyle = COLOURS.fitted["0"]; ctx.fillRect(10, 30, 12, 12);
    ctx.fillStyle = "#333"; ctx.fillText(apart ? "fitted (left)" : "fitted", 28, 41);
    if (truth) {
      ctx.fillStyle = COLOURS.truth["0"]; ctx.fillRect(10, 48, 12, 12);
      ctx.fillStyle = "#333"; ctx.fillText(apart ? "truth (right)" : "truth", 28, 59);
    }
    scrub.value = String(f);
    label.textContent = D.frames[f] + " / " + D.frames[F - 1];
    playBtn.textContent = state.playing ? "Pause" : "Play";
    drawn += 1;
    document.body.setAttribute("data-frames-drawn", String(drawn));
    document.body.setAttribute("data-frame", String(f));
    var rect = canvas.getBoundingClientRect();
    document.body.setAttribute("data-canvas-rect", [Math.round(rect.left + window.scrollX), Math.round(rect.top + window.scrollY),
                                                    Math.round(rect.width), Math.round(rect.height)].join(","));
  }

  function setFrame(f) { state.frame = ((f % F) + F) % F; }

  // playback on a timer rather than requestAnimationFrame, so that it also runs where nothing is
  // composited (headless checks); interactions redraw at once (drawing is cheap)
  var timer = null;
  function step() {
    timer = null;
    if (!state.playing || F < 2) return;
    setFrame(state.frame + 1);
    draw();
    schedule();
  }
  function schedule() {
    if (timer === null && state.playing) timer = window.setTimeout(step, 1000 / (D.rate * parseFloat(speedSel.value)));
  }
  function setPlaying(on) {
    state.playing = on;
    if (!on && timer !== null) { window.clearTimeout(timer); timer = null; }
    draw();
    schedule();
  }

  playBtn.addEventListener("click", function () { setPlaying(!state.playing); });
  scrub.addEventListener("input", function () { state.playing = false; setFrame(parseInt(scrub.value, 10)); setPlaying(false); });
  [truthBox, besideBox, followBox].forEach(function (box) { box.addEventListener("change", draw); });
  var drag = null;
  canvas.addEventListener("pointerdown", function (e) { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointermove", function (e) {
    if (!drag) return;
    state.yaw -= (e.clientX - drag[0]) * 0.01;
    state.pitch = Math.max(-1.45, Math.min(1.45, state.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY];
    draw();
  });
  canvas.addEventListener("pointerup", function () { drag = null; });
  canvas.addEventListener("wheel", function (e) {
    e.preventDefault();
    state.dist = Math.max(1.5, Math.min(15, state.dist * Math.exp(e.deltaY * 0.001)));
    draw();
  }, { passive: false });
  document.addEventListener("keydown", function (e) {
    if (e.target && e.target.tagName === "INPUT" && e.target.type === "range") return;
    if (e.key === " ") { setPlaying(!state.playing); e.preventDefault(); }
    else if (e.key === "ArrowRight") { setFrame(state.frame + 1); setPlaying(false); }
    else if (e.key === "ArrowLeft") { setFrame(state.frame - 1); setPlaying(false); }
  });
  draw();
  schedule();

  // the take's video: its length once the browser has read it (a check that it decodes)
  var take = document.querySelector("video.take");
  function noteVideo() { document.body.setAttribute("data-video-duration", take.duration.toFixed(3)); }
  if (take) {
    if (take.readyState >= 1) noteVideo(); else take.addEventListener("loadedmetadata", noteVideo);
  }
})();
</script>
</body>
</html>
"""
