"""c4g.bench.fit_plot reads fit_clip's CSV as fit_clip writes it (no header, `#` lines, starts, a run
appended twice) and draws the plot."""

from pathlib import Path

from c4g.bench.fit_plot import plot, read

ROWS = """\
bedroom,feed-forward,0,0.0,512,0,25,200,17.46,0.482,15.40,0.485
bedroom,start:fast,0,0.8,513,1,20,200,17.46,0.482,15.49,0.485
bedroom,fast,1300,41.4,9969,3165,20,200,22.49,0.733,22.36,0.743
# fast: fit() 40.6 s (1300 of 1300 steps), held-out at 128 px full frame 15.73 -> 23.77 dB
bedroom,random:fast,1271,55.9,9987,5317,20,200,17.95,0.582,18.06,0.606
bedroom,fast,1300,37.0,9969,3165,20,200,22.50,0.733,22.36,0.743
dog,feed-forward,0,0.0,512,0,25,289,16.79,0.502,14.80,0.448
"""


def test_rows_are_read_by_clip_and_run_the_last_one_counting(tmp_path: Path):
    path = tmp_path / "fit.csv"
    path.write_text(ROWS)
    results = read(path)
    assert set(results) == {"bedroom", "dog"}
    assert results["bedroom"] == {
        "feed-forward": (0.0, 17.46),
        "fast": (37.0, 22.50),
        "random:fast": (55.9, 17.95),
    }
    out = tmp_path / "plot.png"
    plot(results, out)
    assert out.read_bytes().startswith(b"\x89PNG")
