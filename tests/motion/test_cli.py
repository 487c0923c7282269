import pytest

from motion.__main__ import main
from tests.motion.test_bvh import BUNDLED


def test_info_describes_the_bundled_walk(capsys):
    assert main(["info", str(BUNDLED)]) == 0
    out = capsys.readouterr().out
    assert "frames: 344 at 120 Hz" in out
    assert "joints: 31, channels: 96" in out
    assert "units: estimated" in out
    assert "body parts: all 15 mapped" in out
    assert "knee_l: LeftLeg" in out


@pytest.mark.parametrize(
    ("content", "message"), [(None, "No such file"), ("HIERARCHY\nROOT a\n{\n", "no MOTION block")]
)
def test_info_fails_with_one_line_reason(tmp_path, capsys, content, message):
    path = tmp_path / "x.bvh"
    if content is not None:
        path.write_text(content)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and message in err and "\n" not in err
