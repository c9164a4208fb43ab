"""One per-clip loop: ``StreamEstimator`` driven directly on a generated sequence gives, clip by clip, what ``vi3 eval``
reports and what ``vi3 replay`` publishes on ``~/status`` (both drive that same object)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from msg_adapters.diagnostics import diagnostic_array_to_statuses
from vi3_core.backbones import make_backbone
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.calib import write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_core.dataset.sequence import make_clip
from vi3_core.eval.runner import EvalOptions, clip_indices
from vi3_core.online import StreamEstimator
from vi3_ros.cli import main as vi3_main

pytestmark = pytest.mark.slow  # a replay, an evaluation and a direct run of the same sequence


def test_stream_estimator_is_what_eval_and_replay_run(cache_dir, tmp_path, capsys):
    asl = cached_sequence(cache_dir, seconds=4.0, seed=2, with_depth=False)
    seq = read_asl(asl)
    stream = StreamEstimator(make_backbone("classical"))
    direct = []
    for idx in clip_indices(len(seq), options=EvalOptions(clips="sliding"), chained=True):
        clip = make_clip(seq, idx, history_s=stream.online_options.online_max_bridge, lead_s=stream.imu_lead,
                         with_depth=False)
        out = stream.process(clip)
        direct.append((out.init.status.value, out.init.scale_sigma / out.init.scale if out.init.ok else None,
                       out.decision.describe(), out.init.fit.scale_rel_sigma if out.init.fit else np.nan))
    assert len(direct) >= 4 and any(status == "ok" for status, *_ in direct)

    assert vi3_main(["eval", str(asl), "--json", "--no-progress"]) == 0
    evaluated = json.loads(capsys.readouterr().out)
    assert [c["status"] for c in evaluated["clips"]] == [status for status, *_ in direct]
    assert evaluated["chained"]["decisions"] == [d for _, _, d, _ in direct]
    for c, (_, rel, _, _) in zip(evaluated["clips"], direct):
        assert (c["scale_rel_sigma"] is None) == (rel is None)
        if rel is not None:
            assert c["scale_rel_sigma"] == pytest.approx(rel, rel=1e-12)

    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    out = tmp_path / "out.mcap"
    assert vi3_main(["replay", str(asl), "--output", str(out), "--calib", str(calib), "--no-progress"]) == 0
    with AnyReader([out]) as reader:
        statuses = [s for conn, _, raw in reader.messages() if conn.topic == "/vi3_node/status"
                    for s in diagnostic_array_to_statuses(reader.deserialize(raw, conn.msgtype))]
    published = [(s.values["init_status"], float(s.values["scale_rel_sigma"]), s.values["online"]) for s in statuses]
    assert [(st, d) for st, _, d in published] == [(st, d) for st, _, d, _ in direct]
    # ~/status prints 3 significant digits of the fit's relative sigma (NaN where no fit ran)
    np.testing.assert_allclose([got for _, got, _ in published], [fit for *_, fit in direct], rtol=5e-3)
