import numpy as np
import pytest
from PIL import Image

from carp.reporting.image_grid import sample_steps, save_frame_grid


def test_sample_steps_are_evenly_spaced_from_first_to_last():
    assert sample_steps(30, 4) == [0, 10, 19, 29]
    assert sample_steps(3, 6) == [0, 1, 2]
    assert sample_steps(1, 6) == [0]
    with pytest.raises(ValueError, match="length=0, count=6"):
        sample_steps(0, 6)


def test_grid_has_a_row_per_camera_and_a_column_per_sampled_step(tmp_path):
    rng = np.random.default_rng(0)
    images = {key: rng.integers(0, 256, (20, 16, 16, 3), dtype=np.uint8) for key in ("a_image", "b_image")}
    wide = save_frame_grid(images, tmp_path / "wide.png", num_frames=6, title="lift")
    narrow = save_frame_grid({"a_image": images["a_image"]}, tmp_path / "sub" / "narrow.png", num_frames=2)
    with Image.open(wide) as first, Image.open(narrow) as second:
        assert first.size[0] == 3 * second.size[0]  # 6 columns vs 2
        assert first.size[1] > second.size[1]  # 2 rows vs 1


def test_grid_refuses_frames_that_are_not_uint8_rgb(tmp_path):
    with pytest.raises(ValueError, match=r"images\['a_image'\] shape=\(4, 8, 8\), dtype=uint8: expected"):
        save_frame_grid({"a_image": np.zeros((4, 8, 8), dtype=np.uint8)}, tmp_path / "grid.png")
    with pytest.raises(ValueError, match="cameras have different numbers of frames"):
        save_frame_grid(
            {"a_image": np.zeros((4, 8, 8, 3), np.uint8), "b_image": np.zeros((5, 8, 8, 3), np.uint8)},
            tmp_path / "grid.png",
        )
    assert not (tmp_path / "grid.png").exists()
