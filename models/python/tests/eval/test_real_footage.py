"""`c4g.eval.real_footage` on a video FFmpeg makes: the picture has a row per package plus the truth and
the nearest frame, and the scores it prints are PSNRs."""

import re
import shutil
import subprocess

import pytest
from PIL import Image

from c4g.eval import real_footage

from tests.common import MODELS

TINY = MODELS / "c4g-tiny"


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="needs FFmpeg (scripts/setup installs it)")
def test_a_picture_of_each_package_beside_the_truth(tmp_path, capsys):
    video = tmp_path / "clip.mp4"
    subprocess.run(["ffmpeg", "-v", "error", "-f", "lavfi", "-i", "testsrc=size=160x120:rate=30:duration=1.5", "-pix_fmt", "yuv420p", str(video)], check=True)
    out = tmp_path / "picture.png"
    assert real_footage.main(["--package", str(TINY), "--compare", str(TINY), "--video", str(video), "--out", str(out)]) == 0
    picture = Image.open(out)
    # 3 interpolated frames of 64 px across; rows: truth, two packages, nearest frame; 2 px gaps; x3.
    assert picture.size == (3 * 64 * 3, (4 * 64 + 3 * 2) * 3)
    scores = [float(x) for x in re.findall(r"([\d.]+) dB", capsys.readouterr().out)]
    assert len(scores) == 3 and all(5 < s < 60 for s in scores)
    with pytest.raises(ValueError, match="frames from"):
        real_footage.frames_of(video, 1.4, 7, 64)
