"""Sequence folders as users have them: image formats, file names, EasyMocap / ZJU-MoCap layouts,
masks that are not binary, cameras of different sizes, missing files."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from common.calibration import save_calibration
from common.camera import Studio, circle_studio
from common.errors import InputFileError, UserError
from common.sequence import expected_path, frame_files, load_sequence, read_mask, write_sequence_meta

W, H = 64, 48
MIXED_SIZES = ((320, 240), (400, 300), (480, 360))  # width, height


def _studio(sizes) -> Studio:
    """Cameras cam1..camK, camera k of image size sizes[k]."""
    return Studio(tuple(circle_studio(len(sizes), w, h, overhead=False)[k] for k, (w, h) in enumerate(sizes)))


def _mask(w, h, k=0, frame=0) -> np.ndarray:
    """(h, w) bool: a box that moves with the camera and the frame."""
    m = np.zeros((h, w), dtype=bool)
    m[h // 4 + frame:h // 2 + frame + k, w // 3 + k:w // 2 + 2 * k] = True
    return m


def _image(w, h, k=0, frame=0) -> np.ndarray:
    """(h, w, 3) uint8: smooth colours, different per camera and frame."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(x * 3 + k * 40) % 256, (y * 5 + frame * 20) % 256, (x + y) % 256], -1).astype(np.uint8)


def _root(tmp_path, sizes=((W, H), (W, H))):
    root = tmp_path / "seq"
    root.mkdir()
    studio = _studio(sizes)
    save_calibration(studio, root / "calibration.json")
    return root, studio


def _save(path, array, mode=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array, mode).save(path) if mode else Image.fromarray(array).save(path)


# --------------------------------------------------------------------------- names
def test_a_name_alone_is_numbered_by_its_last_run_of_digits(tmp_path):
    for name, number in (("img_2.jpg", 2), ("000010.png", 10), ("cam3_take2_0017.tif", 17)):
        folder = tmp_path / name.split(".")[0]
        folder.mkdir()
        (folder / name).write_bytes(b"")
        (folder / "background.png").write_bytes(b"")  # no digit: no frame
        assert list(frame_files(folder)) == [number]


def test_frame_files_in_natural_order(tmp_path):
    for name in ("img_10.png", "img_2.jpg", "img_1.bmp", "notes.txt", "empty.png", ".hidden_5.png"):
        (tmp_path / name).write_bytes(b"")
    files = frame_files(tmp_path)
    assert list(files) == [1, 2, 10]
    assert [p.name for p in files.values()] == ["img_1.bmp", "img_2.jpg", "img_10.png"]
    assert frame_files(tmp_path / "nope") == {}


def test_the_frame_number_is_the_run_of_digits_that_changes(tmp_path):
    """ZJU-MoCap's CoreView names end in a time stamp, others put the camera after the frame:
    the frame is the run of digits that differs in every file of the folder."""
    zju = tmp_path / "zju"
    zju.mkdir()
    for f, ms in ((1, 592), (2, 625), (3, 658)):
        (zju / f"CoreView_313_Camera_(1)_{f:04d}_2019-08-23_16-08-50.{ms}.png").write_bytes(b"")
    assert list(frame_files(zju)) == [1, 2, 3]
    after = tmp_path / "after"
    after.mkdir()
    for f in (3, 1, 2):
        (after / f"{f:04d}_c1.png").write_bytes(b"")
    assert list(frame_files(after)) == [1, 2, 3]
    assert expected_path(after, frame_files(after), 7) == after / "0007_c1.png"
    stamped = tmp_path / "stamped"  # a time stamp first, in milliseconds: the frame counter is denser
    stamped.mkdir()
    for f in (1, 2, 3):
        (stamped / f"{1571823530000 + 33 * f + f % 2}_{f:06d}.png").write_bytes(b"")
    assert list(frame_files(stamped)) == [1, 2, 3]
    single = tmp_path / "single"  # one file: nothing differs, the last run as for one name alone
    single.mkdir()
    (single / "cam1_000004.png").write_bytes(b"")
    assert list(frame_files(single)) == [4]


def test_two_files_for_one_frame_are_refused(tmp_path):
    (tmp_path / "a_3.png").write_bytes(b"")
    (tmp_path / "b_003.jpg").write_bytes(b"")
    with pytest.raises(InputFileError, match="two files for frame 3: a_3.png and b_003.jpg"):
        frame_files(tmp_path)


def test_frames_on_disk_follow_the_numbers(tmp_path):
    root, studio = _root(tmp_path)
    for cam in studio:
        for f in (10, 2, 1):
            _save(root / "silhouettes" / cam.name / f"img_{f}.png", _mask(W, H, frame=f))
    seq = load_sequence(root)
    assert seq.frames == [1, 2, 10]
    assert np.array_equal(seq.silhouettes(10)[0], _mask(W, H, frame=10))


# --------------------------------------------------------------------------- formats
MASK_FORMATS = [  # suffix, how the mask is stored
    (".png", "1"), (".png", "L"), (".bmp", "1"), (".pbm", "1"), (".pgm", "L"), (".ppm", "RGB"),
    (".tif", "1"), (".tiff", "L"),
]


@pytest.mark.parametrize("suffix,mode", MASK_FORMATS)
def test_mask_formats(tmp_path, suffix, mode):
    root, studio = _root(tmp_path)
    masks = [_mask(W, H, k) for k in range(2)]
    for k, cam in enumerate(studio):
        m = masks[k]
        stored = {"1": m, "L": m.astype(np.uint8) * 255, "RGB": np.repeat(m[..., None], 3, -1).astype(np.uint8) * 255}
        _save(root / "silhouettes" / cam.name / f"{7:06d}{suffix}", stored[mode])
    seq = load_sequence(root)
    assert seq.frames == [7]
    got = seq.silhouettes(7)
    assert got.dtype == bool and np.array_equal(got, np.stack(masks))


@pytest.mark.parametrize("suffix", [".png", ".bmp", ".ppm", ".tif", ".jpg", ".jpeg"])
def test_image_formats(tmp_path, suffix):
    root, studio = _root(tmp_path)
    images = [_image(W, H, k, 3) for k in range(2)]
    for k, cam in enumerate(studio):
        _save(root / "images" / cam.name / f"frame_3{suffix}", images[k])
    got = load_sequence(root).images(3)
    assert got.dtype == np.uint8 and got.shape == (2, H, W, 3)
    error = np.abs(got.astype(int) - np.stack(images)).mean()
    assert error < (8.0 if suffix in (".jpg", ".jpeg") else 1e-9)


@pytest.mark.parametrize("masks_folder,sizes_written", [("mask", True), ("masks", True), ("mask", False)])
def test_easymocap_layout(tmp_path, capsys, masks_folder, sizes_written):
    """EasyMocap / ZJU-MoCap: images/<cam>/000000.jpg, mask(s)/<cam>/000000.png (0/1), intri.yml + extri.yml,
    with image sizes or, as EasyMocap's write_intri writes it, without (then the images' sizes)."""
    root = tmp_path / "easymocap"
    studio = _studio(((W, H), (W, H), (W, H)))
    save_calibration(studio, root, fmt="easymocap")
    if not sizes_written:
        intri = root / "intri.yml"
        intri.write_text("".join(line for line in intri.read_text().splitlines(keepends=True)
                                 if not line.startswith(("H_", "W_"))))
    for k, cam in enumerate(studio):
        for f in range(3):
            _save(root / "images" / cam.name / f"{f:06d}.jpg", _image(W, H, k, f))
            _save(root / masks_folder / cam.name / f"{f:06d}.png", _mask(W, H, k, f).astype(np.uint8))  # 0 / 1
    seq = load_sequence(root)
    assert seq.studio.names == studio.names and seq.frames == [0, 1, 2] and seq.has_silhouettes
    assert np.array_equal(seq.silhouettes(2), np.stack([_mask(W, H, k, 2) for k in range(3)]))
    assert seq.images(1).shape == (3, H, W, 3)
    seq.check_files(seq.frames, images=True)
    assert seq.constant_cameras(seq.frames) == {}
    assert all((c.width, c.height) == (W, H) and not c.size_guessed for c in seq.user_studio)
    assert "guessed" not in capsys.readouterr().err  # the sizes are the images', not guesses


@pytest.mark.timeout(60)
def test_calibration_json_beside_easymocap_files_is_refused(tmp_path, capsys):
    """A sequence reads calibration.json or EasyMocap's intri.yml + extri.yml: with both, the one
    edited last might not be the one read, so the sequence is refused naming both."""
    from server.cli import main

    root, studio = _root(tmp_path)
    for k, cam in enumerate(studio):
        _save(root / "silhouettes" / cam.name / "000000.png", _mask(W, H, k).astype(np.uint8) * 255)
    save_calibration(studio, root, fmt="easymocap")
    expected = f"{root}: <folder>: holds 2 calibrations: calibration.json and intri.yml + extri.yml; keep one"
    with pytest.raises(UserError) as info:
        load_sequence(root)
    assert str(info.value) == expected
    assert main(["fit", str(root), "--out", str(tmp_path / "result")]) == 2 and not (tmp_path / "result").exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and err.strip().endswith(expected), err
    (root / "calibration.json").unlink()
    assert load_sequence(root).studio.names == studio.names


# --------------------------------------------------------------------------- non-binary masks
def test_colour_and_grey_masks_need_a_threshold(tmp_path):
    root, studio = _root(tmp_path)
    m = _mask(W, H)
    grey = np.where(m, 200, 0).astype(np.uint8)
    grey[0, 0] = 90  # a third level
    colour = np.zeros((H, W, 3), dtype=np.uint8)
    colour[m] = (255, 200, 0)  # grey level 193
    _save(root / "silhouettes" / "cam1" / "000000.png", grey)
    _save(root / "silhouettes" / "cam2" / "000000.png", colour)
    with pytest.raises(InputFileError, match=r"cam1/000000.png: a grey image, not a mask .*--mask-threshold"):
        load_sequence(root).silhouettes(0)
    with pytest.raises(InputFileError, match=r"cam1/000000.png: a grey image"):
        load_sequence(root).check_files([0])
    with pytest.raises(InputFileError, match=r"cam2/000000.png: a colour image, not a mask"):
        read_mask(root / "silhouettes" / "cam2" / "000000.png")
    got = load_sequence(root, mask_threshold=100).silhouettes(0)
    assert np.array_equal(got[0], m) and np.array_equal(got[1], m)


def test_jpeg_masks_with_a_threshold(tmp_path):
    root, studio = _root(tmp_path)
    for k, cam in enumerate(studio):
        _save(root / "silhouettes" / cam.name / "000000.jpg", _mask(W, H, k).astype(np.uint8) * 255)
    with pytest.raises(InputFileError, match="000000.jpg: a grey image, not a mask"):
        load_sequence(root).silhouettes(0)
    got = load_sequence(root, mask_threshold=127).silhouettes(0)
    truth = np.stack([_mask(W, H, k) for k in range(2)])
    assert np.count_nonzero(got != truth) <= 0.01 * truth.size


def test_label_map_masks_and_thresholds_past_8_bits(tmp_path):
    """A palette PNG of two colours (black and a label's colour) is a mask; an 8-bit mask with
    a threshold no grey level exceeds is refused, naming the file."""
    root, studio = _root(tmp_path)
    m = _mask(W, H)
    for cam in studio:
        label = Image.fromarray(m.astype(np.uint8), "L").convert("P")
        label.putpalette([0, 0, 0, 192, 128, 128] + [0] * 762)
        path = root / "silhouettes" / cam.name / "000000.png"
        path.parent.mkdir(parents=True)
        label.save(path)
    assert Image.open(path).mode == "P" and np.array_equal(read_mask(path), m)
    assert np.array_equal(load_sequence(root).silhouettes(0)[1], m)
    with pytest.raises(InputFileError, match=r"cam2/000000.png: an 8-bit image: no grey level is above the mask "
                                             r"threshold 255 \(0..254 for 8-bit masks\)"):
        read_mask(path, 255)
    assert not read_mask(path, 254).any() and read_mask(path, 0).sum() == m.sum()


@pytest.mark.parametrize("threshold", [-1, 1.5, "127", True, 70000])
def test_bad_mask_threshold(tmp_path, threshold):
    root, _ = _root(tmp_path)
    with pytest.raises(UserError, match="mask threshold"):
        load_sequence(root, mask_threshold=threshold)


def test_masks_all_on_or_off_in_every_frame_are_found(tmp_path):
    root, studio = _root(tmp_path, ((W, H),) * 3)
    for f in range(4):
        _save(root / "silhouettes" / "cam1" / f"{f:06d}.png", _mask(W, H, 0, f))
        _save(root / "silhouettes" / "cam2" / f"{f:06d}.png", np.zeros((H, W), dtype=bool))
        _save(root / "silhouettes" / "cam3" / f"{f:06d}.png", np.full((H, W), f % 2 == 0))
    seq = load_sequence(root)
    assert seq.constant_cameras(range(4)) == {"cam2": "off", "cam3": "on or off"}
    fewer = seq.without_cameras(["cam2", "cam3"])
    assert fewer.studio.names == fewer.user_studio.names == ["cam1"] and seq.studio.names == ["cam1", "cam2", "cam3"]
    assert fewer.silhouettes(1).shape == (1, H, W) and np.array_equal(fewer.silhouettes(1)[0], _mask(W, H, 0, 1))
    # a check passed is not read again, for the same cameras or fewer; for more it is
    read = []
    for s in (seq, fewer):
        s.mask = lambda cam, frame, s=s, own=s.mask: read.append(cam.name) or own(cam, frame)
    fewer.check_files(range(4))
    seq.check_files(range(4))
    assert read == ["cam1"] * 4 + ["cam1", "cam2", "cam3"] * 4
    seq.check_files(range(4))
    fewer.check_files(range(4))
    assert len(read) == 16


# --------------------------------------------------------------------------- mixed sizes
def test_mixed_camera_sizes_are_padded(tmp_path):
    root, studio = _root(tmp_path, MIXED_SIZES)
    for k, (w, h) in enumerate(MIXED_SIZES):
        _save(root / "silhouettes" / f"cam{k + 1}" / "000004.png", _mask(w, h, k, 4))
        _save(root / "images" / f"cam{k + 1}" / "000004.png", _image(w, h, k, 4))
    seq = load_sequence(root)
    assert seq.padded_shape == (360, 480)
    masks, images = seq.silhouettes(4), seq.images(4)
    assert masks.shape == (3, 360, 480) and masks.dtype == bool
    assert images.shape == (3, 360, 480, 3) and images.dtype == np.uint8
    for k, (w, h) in enumerate(MIXED_SIZES):
        assert np.array_equal(masks[k, :h, :w], _mask(w, h, k, 4))
        assert np.array_equal(images[k, :h, :w], _image(w, h, k, 4))
        assert not masks[k, h:].any() and not masks[k, :, w:].any()
        assert not images[k, h:].any() and not images[k, :, w:].any()


def test_each_file_is_checked_against_its_own_camera(tmp_path):
    root, studio = _root(tmp_path, MIXED_SIZES)
    for k, (w, h) in enumerate(MIXED_SIZES):
        w, h = MIXED_SIZES[0] if k == 1 else (w, h)  # cam2 written at cam1's size, which fits the padding
        _save(root / "silhouettes" / f"cam{k + 1}" / "000000.png", _mask(w, h))
    with pytest.raises(InputFileError, match=r"cam2/000000.png: size 320x240 does not match the calibration "
                                             r"of cam2 \(400x300\)"):
        load_sequence(root).silhouettes(0)


# --------------------------------------------------------------------------- missing files
@pytest.mark.parametrize("lacking,listed", [("cam2", True), ("cam1", False)])
def test_check_files_names_the_first_missing_file(tmp_path, lacking, listed):
    """With sequence.json or without (then the frames are those any camera has a file for, so
    a frame the first camera lacks is named, not dropped)."""
    root, studio = _root(tmp_path)
    for f in range(3):
        for cam in studio:
            _save(root / "silhouettes" / cam.name / f"img_{f:04d}.png", _mask(W, H, frame=f))
    (root / "silhouettes" / lacking / "img_0001.png").unlink()
    if listed:
        write_sequence_meta(root, [0, 1, 2], 30.0, studio.names)
    seq = load_sequence(root)
    assert seq.frames == [0, 1, 2]
    with pytest.raises(InputFileError, match=rf"silhouettes/{lacking}/img_0001.png: missing: frame 1 of camera "
                                             rf"{lacking}"):
        seq.check_files(seq.frames)
    seq.check_files([0, 2])
    with pytest.raises(InputFileError, match="img_0001.png: missing"):
        seq.silhouettes(1)


def test_check_files_unreadable_and_absent_folders(tmp_path):
    root, studio = _root(tmp_path)
    for cam in studio:
        _save(root / "silhouettes" / cam.name / "000000.png", _mask(W, H))
    (root / "silhouettes" / "cam1" / "000000.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    write_sequence_meta(root, [0], 30.0, studio.names)
    seq = load_sequence(root)
    with pytest.raises(InputFileError, match=r"cam1/000000.png: not a readable image"):
        seq.check_files([0])
    # no images/ at all: said of the folder, not of its first file
    with pytest.raises(InputFileError, match=r"images/cam1: missing: no folder for camera cam1 \(images/ holds no "
                                             r"camera folder\)"):
        seq.check_files([0], masks=False, images=True)
    (root / "images" / "cam2").mkdir(parents=True)
    with pytest.raises(InputFileError, match=r"images/cam1: missing: no folder for camera cam1 \(holds cam2\)"):
        load_sequence(root).check_files([0], masks=False, images=True)
    (tmp_path / "bare").mkdir()
    bare, _ = _root(tmp_path / "bare")
    write_sequence_meta(bare, [0], 30.0, studio.names)
    with pytest.raises(InputFileError, match="no silhouettes"):
        load_sequence(bare).check_files([0])
