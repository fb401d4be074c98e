"""Refinement jobs end to end: submitted through the client, run by the tiny refiner worker,
followed as server-sent events with progress, their result fetched; and cancelled."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client


def test_a_queued_job_is_cancelled_at_once(client: Client, clip: c4g.Clip):
    # No worker runs during this test: the job stays queued until cancelled.
    job = client.refine(clip.id, steps=2, seed=7)
    assert job.state == "queued" and job.clip_id == clip.id and not job.is_terminal
    cancelled = client.cancel(job.id)
    assert cancelled.state == "cancelled" and cancelled.is_terminal
    (last,) = list(client.follow(job.id))
    assert last.state == "cancelled"
    # No result: the server answers 400 invalid_input for a cancelled job (404 while queued).
    with pytest.raises((c4g.InvalidInput, c4g.NotFound)):
        client.job_result(job.id)


def test_a_refinement_runs_on_the_worker_and_its_result_is_fetched(
    client: Client, clip: c4g.Clip, refiner, tmp_path: Path
):
    job = client.refine(
        clip.id,
        trajectory=c4g.Orbit(depth=2.0, angle_degrees=20),
        steps=2,
        caption=None,
        seed=1,
    )
    assert job.id in [j.id for j in client.jobs()]
    seen = []
    done = client.wait(job.id, progress=seen.append)
    assert done.state == "done" and done.is_done, (done.error, refiner.tail())
    assert seen[-1] == done and all(isinstance(j, c4g.Job) for j in seen)
    steps = [j.progress.step for j in seen if j.progress is not None]
    assert steps and steps == sorted(steps) and seen[-1].progress.steps == 2
    assert client.job(job.id).state == "done" and done.result_frames > 0

    video = client.job_result(job.id, path=tmp_path / "refined.mp4")
    assert video.data[4:8] == b"ftyp" and (tmp_path / "refined.mp4").read_bytes() == video.data
    frame = client.job_frame(job.id, 0)
    assert frame.array.ndim == 3 and frame.array.dtype == np.uint8
    with pytest.raises(c4g.NotFound):
        client.job_frame(job.id, done.result_frames + 5)
    # A job that has ended is left as it is.
    assert client.cancel(job.id).state == "done"


def test_unknown_jobs_are_not_found_and_bad_requests_invalid(client: Client, clip: c4g.Clip):
    with pytest.raises(c4g.NotFound):
        client.job("job-" + "0" * 20)
    with pytest.raises(c4g.NotFound):
        client.follow("job-" + "0" * 20)
    with pytest.raises(c4g.NotFound):
        client.refine("0" * 24, steps=2)
    with pytest.raises(c4g.InvalidInput):
        client.refine(clip.id, steps=0)
