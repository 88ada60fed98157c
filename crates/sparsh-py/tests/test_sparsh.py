"""Tests of the installed `sparsh` package: each asserts against an independent answer (force as
the integral of the traction field, a NumPy transcription of the official preprocessing, the
files `generate` writes against the simulator's frames, Hertz's solution), not against output
captured once. PyTorch's tests run where torch imports (SPARSH_REQUIRE_TORCH=1 makes its absence
a failure)."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import sparsh
from sparsh.dataset import GeneratedFrames, simulated_frames

REPO = Path(__file__).resolve().parents[3]

# Three short press-and-slide sequences on a DIGIT, on the bonded-layer rung at a 4-pixel stride.
FAMILY = """
seed = 3

[output]
fields = ["p", "qx", "qy", "uz", "contact", "slip"]

[[family]]
name = "press_slide"
sequences = 3
frames_per_sequence = 9
solver = "layered"
mechanics_stride = 4
[family.sensor]
preset = "digit"
[family.gel]
youngs_modulus_kpa = 300.0
poisson_ratio = 0.48
thickness_mm = 3.0
friction = 1.0
[[family.indenters]]
shape = "sphere"
radius_mm = [3.0, 5.0]
[family.motion]
kind = "press_slide"
depth_mm = [0.3, 0.6]
slide_mm = [0.5, 1.0]
start_x_mm = [-1.0, 1.0]
start_y_mm = [-1.0, 1.0]
"""


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "family.toml"
    path.write_text(FAMILY)
    return path


@pytest.fixture(scope="module")
def dataset(scene_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "family"
    report = sparsh.generate(scene_file, out)
    assert report["frames"] == 27 and report["complete"], report
    return out


def frames_of(scene_file, sequence, threads=None):
    return list(sparsh.Scene(scene_file).simulate(sequence, threads=threads))


def test_scene_counts(scene_file):
    scene = sparsh.Scene(scene_file)
    assert (scene.sequences, scene.frames, scene.seed) == (3, 27, 3)
    info = scene.sequence(2)
    assert info["frames"] == 9 and info["family"] == "press_slide" and info["solver"] == "layered"
    assert (info["width_px"], info["height_px"]) == (320, 240)


def test_frame_force_is_the_integral_of_its_traction(scene_file):
    frames = frames_of(scene_file, 0)
    assert len(frames) == 9
    pressed = 0
    for f in frames:
        image, fields, label = f["image"], f["fields"], f["label"]
        assert image.shape == (240, 320, 3) and image.dtype == np.uint8
        assert fields["p"].shape == (60, 80) and fields["contact"].dtype == bool
        area = f["cell_mm"] ** 2
        # kPa · mm² = mN
        integral = [1e-3 * area * fields[c].sum() for c in ("qx", "qy", "p")]
        assert np.allclose(label["force_n"], integral, rtol=1e-9, atol=1e-12), (label["force_n"], integral)
        assert not np.any(fields["slip"] & ~fields["contact"])
        assert np.all(fields["p"][~fields["contact"]] == 0)
        pressed += label["force_n"][2] > 0.05
    assert pressed >= 3


def test_same_bits_whatever_the_thread_count(scene_file):
    one, two = frames_of(scene_file, 1, threads=1), frames_of(scene_file, 1, threads=2)
    for a, b in zip(one, two):
        assert np.array_equal(a["image"], b["image"])
        for c in a["fields"]:
            assert np.array_equal(a["fields"][c], b["fields"][c])
        assert a["label"] == b["label"]


def test_generate_writes_what_the_simulator_gives(scene_file, dataset):
    lines = sparsh.verify(dataset)
    assert any("match the manifest" in line for line in lines), lines
    rows = [json.loads(line) for line in (dataset / "labels.jsonl").read_text().splitlines()]
    assert len(rows) == 27
    sim = sparsh.Scene(scene_file).simulate(2)
    assert np.array_equal(sparsh.read_image(dataset / rows[18]["background"]), sim.background)
    for row, frame in zip(rows[18:], sim):
        assert row == frame["label"]
        assert np.array_equal(sparsh.read_image(dataset / "frames" / f"{row['frame']:06}.png"), frame["image"])
        stored = sparsh.read_fields(dataset / "fields" / f"{row['frame']:06}.exr")
        assert sorted(stored) == ["contact", "p", "qx", "qy", "slip", "uz"]
        assert np.array_equal(stored["p"], frame["fields"]["p"].astype(np.float32))
        assert np.array_equal(stored["slip"], frame["fields"]["slip"].astype(np.float32))


def official_preprocess(img, bg):
    """`compute_diff` and `load_sample_from_buf` of the official data/digit/utils.py, in NumPy,
    without the final resize: int32 difference /255 + 0.5, clipped, uint8; turned clockwise; the
    4:3 centre crop."""
    diff = (img.astype(np.int32) - bg.astype(np.int32)) / 255.0 + 0.5
    diff = np.uint8(np.clip(diff, 0.0, 1.0) * 255.0)
    h, w, _ = diff.shape
    if h < w:
        diff = np.rot90(diff, k=-1)  # cv2.ROTATE_90_CLOCKWISE
    h, w, _ = diff.shape
    r = 4 / 3
    if h / w != r:
        h2 = int(h / r)
        diff = diff[int((h - h2) / 2) : int((h + h2) / 2)]
    return np.ascontiguousarray(diff.transpose(2, 0, 1)).astype(np.float32) / np.float32(255.0)


def test_preprocess_is_the_official_code():
    rng = np.random.default_rng(0)
    for h, w in [(240, 320), (120, 200), (200, 150)]:
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        bg = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        want = official_preprocess(img, bg)
        got = sparsh.preprocess(img, bg, size=want.shape[1:])
        assert got.shape == want.shape and got.dtype == np.float32
        assert np.array_equal(got, want), (h, w, np.abs(got - want).max())
    # without a background: the frame itself, turned and scaled
    img = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    got = sparsh.preprocess(img, None, size=(320, 240))
    assert np.array_equal(got, np.rot90(img, k=-1).transpose(2, 0, 1) / np.float32(255.0))
    # resized to the official 320×240 from a portrait frame twice as large: a linear ramp stays
    # the ramp sampled at the new pixel centres (the triangle filter is symmetric), inside a border
    r, c = np.mgrid[0:640, 0:480]
    ramp = np.round(0.25 * r + 0.15 * c).astype(np.uint8)
    small = sparsh.preprocess(np.repeat(ramp[..., None], 3, axis=2), None, size=(320, 240))
    i, j = np.mgrid[0:320, 0:240]
    want = (0.25 * (2 * i + 0.5) + 0.15 * (2 * j + 0.5)) / 255.0
    assert np.abs(small[1] - want)[2:-2, 2:-2].max() < 1 / 255


def test_generated_frames_pair_and_label(dataset):
    frames = GeneratedFrames(dataset, fields=("p", "uz"))
    assert len(frames) == 27
    rows = frames.labels
    bg = sparsh.read_image(dataset / rows[0]["background"])
    for i in (0, 3, 7):
        item = frames[i]
        assert item["image"].shape == (6, 320, 240) and item["image"].dtype == np.float32
        back = rows[max(i - 5, 0)]["frame"]  # the official loader clips t − 5 to the first frame
        for half, frame in ((0, rows[i]["frame"]), (1, back)):
            img = sparsh.read_image(dataset / "frames" / f"{frame:06}.png")
            assert np.array_equal(item["image"][3 * half : 3 * half + 3], official_preprocess(img, bg))
        assert np.array_equal(item["force_n"], np.float32(rows[i]["force_n"]))
        assert item["slip_cone"] == rows[i]["slip_cone"] and item["frame"] == rows[i]["frame"]
        assert set(item["fields"]) == {"p", "uz"} and item["fields"]["uz"].shape == (60, 80)
    assert len(GeneratedFrames(dataset, split="test")) + len(GeneratedFrames(dataset, split="train")) == 27
    single = GeneratedFrames(dataset, offsets=(0,), background=False, size=(160, 120))[4]
    assert single["image"].shape == (3, 160, 120)


def test_simulated_frames_equal_the_generated_ones(scene_file, dataset):
    stored = GeneratedFrames(dataset, fields=("p", "slip"))
    for k, item in enumerate(simulated_frames(scene_file, 1, fields=("p", "slip"))):
        want = stored[9 + k]
        assert np.array_equal(item["image"], want["image"])
        assert np.array_equal(item["force_n"], want["force_n"])
        for c in ("p", "slip"):
            assert np.array_equal(item["fields"][c], want["fields"][c])


def test_validate_against_hertz(tmp_path):
    shutil.copy(REPO / "scenes" / "validation" / "hertz.toml", tmp_path)
    report = sparsh.validate(tmp_path)
    rows = {r["quantity"]: r for r in report["rows"]}
    assert report["passed"] and "force (N)" in rows
    # Hertz: F = 4/3 E* √R δ^{3/2}, E* = E/(1 − ν²): 100 mm sphere, 0.01 mm into 300 kPa, ν 0.48
    e_star = 300e3 / (1 - 0.48**2)
    force = 4 / 3 * e_star * np.sqrt(0.1) * 1e-5**1.5
    assert rows["force (N)"]["analytic"] == pytest.approx(force, rel=1e-12)
    assert rows["force (N)"]["simulated"] == pytest.approx(force, rel=0.01)


def test_bad_input_is_one_clear_error(scene_file, dataset, tmp_path):
    with pytest.raises(sparsh.SparshError, match="nowhere.toml"):
        sparsh.Scene(tmp_path / "nowhere.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text(FAMILY.replace("poisson_ratio = 0.48", "poisson_ratio = 0.7"))
    with pytest.raises(sparsh.SparshError, match="poisson_ratio"):
        sparsh.Scene(bad)
    with pytest.raises(sparsh.SparshError, match="sequence 3 asked for, the file draws 3"):
        sparsh.Scene(scene_file).simulate(3)
    with pytest.raises(sparsh.SparshError, match="threads"):
        sparsh.Scene(scene_file).simulate(0, threads=0)
    not_png = tmp_path / "frame.png"
    not_png.write_bytes(b"not an image")
    with pytest.raises(sparsh.SparshError, match="frame.png: cannot decode image"):
        sparsh.read_image(not_png)
    with pytest.raises(sparsh.SparshError, match="nowhere.exr"):
        sparsh.read_fields(tmp_path / "nowhere.exr")
    img = np.zeros((240, 320, 3), np.uint8)
    with pytest.raises(sparsh.SparshError, match="background"):
        sparsh.preprocess(img, np.zeros((320, 240, 3), np.uint8))
    with pytest.raises(sparsh.SparshError, match="image: expected a"):
        sparsh.preprocess(np.zeros((240, 320, 4), np.uint8))
    with pytest.raises(FileNotFoundError, match="labels.jsonl"):
        GeneratedFrames(tmp_path)
    with pytest.raises(ValueError, match="fields: unknown channel 'bogus'"):
        GeneratedFrames(dataset, fields=("bogus",))
    with pytest.raises(ValueError, match="offsets"):
        GeneratedFrames(dataset, offsets=(0, -5))
    with pytest.raises(sparsh.SparshError, match="not empty"):
        sparsh.generate(scene_file, dataset)
    with pytest.raises(sparsh.SparshError, match="shard"):
        sparsh.generate(scene_file, tmp_path / "sharded", shard="3/2")


def test_verify_finds_a_damaged_file(scene_file, dataset, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    frame = copy / "frames" / "000004.png"
    frame.write_bytes(frame.read_bytes()[:-10])
    with pytest.raises(sparsh.SparshError, match="000004.png"):
        sparsh.verify(copy)


def torch_or_skip():
    if os.environ.get("SPARSH_REQUIRE_TORCH") == "1":
        import torch  # noqa: F401  (fails the test where torch is required)
    return pytest.importorskip("torch")


def test_torch_dataloader_workers_batch_generated_frames(dataset):
    torch = torch_or_skip()
    from sparsh.torch import GeneratedDataset

    loader = torch.utils.data.DataLoader(GeneratedDataset(dataset), batch_size=4, num_workers=2)
    batches = list(loader)
    assert sum(len(b["frame"]) for b in batches) == 27
    first = batches[0]
    assert first["image"].shape == (4, 6, 320, 240) and first["force_n"].shape == (4, 3)
    direct = GeneratedFrames(dataset)[2]
    assert torch.equal(first["image"][2], torch.from_numpy(direct["image"]))


def test_torch_simulated_dataset_shards_sequences_among_workers(scene_file):
    torch = torch_or_skip()
    from sparsh.torch import SimulatedDataset

    data = SimulatedDataset(scene_file, offsets=(0,), size=(160, 120), threads=1)
    loader = torch.utils.data.DataLoader(data, batch_size=None, num_workers=2)
    seen = [(int(item["sequence"]), int(item["frame"])) for item in loader]
    assert sorted(seen) == [(s, f) for s in range(3) for f in range(9 * s, 9 * s + 9)]
    with pytest.raises(ValueError, match="sequences: 5"):
        SimulatedDataset(scene_file, sequences=[5])


def test_torch_one_training_step(dataset):
    torch = torch_or_skip()
    from sparsh.torch import GeneratedDataset

    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Conv2d(6, 8, 5, stride=4), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1), torch.nn.Flatten(), torch.nn.Linear(8, 3))
    optimizer = torch.optim.SGD(model.parameters(), lr=1e-2)
    batch = next(iter(torch.utils.data.DataLoader(GeneratedDataset(dataset), batch_size=8, shuffle=True)))
    before = [p.detach().clone() for p in model.parameters()]
    loss = torch.nn.functional.mse_loss(model(batch["image"]), batch["force_n"])
    loss.backward()
    optimizer.step()
    assert torch.isfinite(loss)
    assert all(not torch.equal(a, b) for a, b in zip(before, model.parameters()))
