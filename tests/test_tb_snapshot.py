"""experiments/tb_snapshot.py: the TensorBoard scalar dashboard of a run, as one PNG."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest
import tb_snapshot

from dicrl_torch.logger import TensorBoardLogger

# Values exact in float32 (TensorBoard stores scalars as float32), so they compare exactly.
WRITTEN = {
    "learner0": {"outer/multiplier": {0: -1.0, 1: -2.5, 2: -3.25}, "eval/FPR": {0: 0.5, 1: 0.25}},
    "network": {"consensus/max_pairwise_cost_distance": {0: 2.0, 1: 0.125}},
}


@pytest.fixture
def run_dir(tmp_path):
    logger = TensorBoardLogger(tmp_path / "tb")  # what train.py writes with
    for run, tags in WRITTEN.items():
        for tag, points in tags.items():
            for step, value in points.items():
                logger.scalar(run, tag, value, step)
    image = np.zeros((8, 12, 3), dtype=np.uint8)
    image[:, :6] = 255
    logger.image("learner0", "eval/constraint_map", image, 0)
    logger.image("learner0", "eval/constraint_map", 255 - image, 3)
    logger.close()
    return tmp_path


def test_read_scalars_returns_what_was_written(run_dir):
    scalars = tb_snapshot.read_scalars(run_dir)
    expected: dict[str, dict[str, dict[int, float]]] = {}
    for run, tags in WRITTEN.items():
        for tag, points in tags.items():
            expected.setdefault(tag, {})[run] = points
    assert {t: set(r) for t, r in scalars.items()} == {t: set(r) for t, r in expected.items()}
    for tag, runs in expected.items():
        for run, points in runs.items():
            steps, values = scalars[tag][run]
            np.testing.assert_array_equal(steps, list(points))
            np.testing.assert_array_equal(values, list(points.values()))


def test_last_image_is_the_latest_step(run_dir):
    run, step, img = tb_snapshot.last_image(run_dir, "eval/constraint_map")
    assert (run, step, img.shape[:2]) == ("learner0", 3, (8, 12))
    assert img[0, 0, 0] == 0 and img[0, -1, 0] == 1  # 255 - image, read back in [0, 1]


def test_main_writes_a_png(run_dir, capsys):
    out = tb_snapshot.main([str(run_dir), "--image", "eval/constraint_map"])
    assert out == run_dir / "tensorboard_scalars.png"
    assert capsys.readouterr().out.strip() == str(out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
    assert matplotlib.image.imread(out).shape[:2] == (800, 1400)
    custom = tb_snapshot.main([str(run_dir), "--tags", "eval/FPR", "--out",
                               str(run_dir / "sub" / "one.png")])
    assert custom.is_file()


def test_missing_tb_dir_and_empty_tb_dir(tmp_path):
    with pytest.raises(ValueError, match="does not exist; give the run directory"):
        tb_snapshot.read_scalars(tmp_path)
    (tmp_path / "tb" / "learner0").mkdir(parents=True)
    with pytest.raises(ValueError, match="No TensorBoard event files"):
        tb_snapshot.read_scalars(tmp_path)
    with pytest.raises(SystemExit, match="error: .* does not exist"):
        tb_snapshot.main([str(tmp_path / "nowhere")])


def test_unknown_tags_list_the_available_ones(run_dir):
    with pytest.raises(ValueError, match=r"\['outer/typo'\].*available.*eval/FPR"):
        tb_snapshot.render(run_dir, ["eval/FPR", "outer/typo"])
    with pytest.raises(ValueError, match="image tag 'eval/nope'.*eval/constraint_map"):
        tb_snapshot.render(run_dir, image="eval/nope")
    with pytest.raises(SystemExit, match="outer/typo"):
        tb_snapshot.main([str(run_dir), "--tags", "outer/typo"])
