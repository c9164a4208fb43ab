"""The ``threads`` parameter and ``vi3 bench --threads``: checked, and set once for the process before the node's
worker thread runs torch."""

from __future__ import annotations

import threading

import cv2
import pytest
import torch

from msg_adapters.types import jazzy_types
from vi3_core.backbones import make_backbone
from vi3_core.errors import DataError
from vi3_core.threads import default_threads
from vi3_ros.calibration import Calibration
from vi3_ros.cli import build_parser
from vi3_ros.params import resolve
from vi3_ros.pipeline import Pipeline
from vi3_ros.replay import McapSink
from vi3_ros.worker import Worker


def test_threads_parameter_is_checked():
    assert resolve().model.threads == 0 and resolve({"threads": "3"}).model.threads == 3
    with pytest.raises(DataError, match=r"threads: -1 is outside \[0, 1024\]"):
        resolve({"threads": -1})
    with pytest.raises(DataError, match=r"threads: expected int in \[0, 1024\], got 'two'"):
        resolve({"threads": "two"})
    assert build_parser().parse_args(["bench", "ttr", "--threads", "1"]).threads == 1
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "ttr", "--threads", "-1"])


@pytest.mark.parametrize("threads", [1, 2, 0])
def test_the_pipeline_sets_torch_threads_for_its_worker_thread(threads, tmp_path):
    """The count is set when the pipeline starts; a worker thread started afterwards (the pipeline's own, or the
    one here, which records what it sees) runs torch with it. 0: ``default_threads()``."""
    want = threads or default_threads()
    seen: list[int] = []
    before = torch.get_num_threads()
    try:
        types = jazzy_types()
        sink = McapSink(tmp_path / "out.mcap", types=types)
        pipeline = Pipeline(resolve({"threads": threads}), backbone=make_backbone("classical"),
                            calibration=Calibration(), sink=sink, types=types)
        done = threading.Event()

        def record(job: str) -> None:
            seen.append(torch.get_num_threads())
            done.set()

        worker = Worker(record, on_error=lambda job, exc: None)
        worker.submit("job")
        assert done.wait(timeout=30.0)
        worker.stop(timeout=10.0)
        pipeline.close(timeout=10.0)
        sink.abandon()
    finally:
        torch.set_num_threads(before)
    assert pipeline.threads == want and seen == [want]
    assert cv2.getNumThreads() == want  # OpenCV's pool (tracking, the plane sweep) too
