import numpy as np
import pytest
import torch

from motion.draw import contact_sheet, draw_parts, draw_skeleton, write_video
from motion.features import read_video
from motion.render import ProjectedParts


def test_skeleton_and_parts_are_drawn_where_they_are():
    img = np.zeros((50, 60, 3), dtype=np.uint8)
    out = draw_skeleton(img, np.array([[10, 10], [40, 10]]), [-1, 0])
    assert out[10, 25].any() and not out[40, 25].any() and not img.any()
    parts = ProjectedParts(
        torch.tensor([[[10.0, 30.0], [50.0, 30.0]]]),
        torch.tensor([[5.0, 5.0]]),
        torch.tensor([[1.0, 1.0]]),
    )
    over = draw_parts(img, parts)
    assert over[30, 30].any() and not over[5, 5].any()


def test_contact_sheet_layout_and_errors():
    tiles = [np.full((20, 30, 3), i * 40, dtype=np.uint8) for i in range(5)]
    sheet = contact_sheet(tiles, columns=3, captions=list("abcde"))
    assert sheet.shape == (2 * 24 + 4, 3 * 34 + 4, 3)
    with pytest.raises(ValueError, match="one size"):
        contact_sheet([tiles[0], np.zeros((5, 5, 3), np.uint8)])


def test_video_round_trip(tmp_path):
    frames = [np.full((32, 48, 3), v, dtype=np.uint8) for v in (0, 128, 255)]
    path = write_video(tmp_path / "x.avi", frames, fps=10)
    back = read_video(path)
    assert back.shape == (3, 32, 48, 3)
    assert abs(int(back[1].mean()) - 128) < 8
