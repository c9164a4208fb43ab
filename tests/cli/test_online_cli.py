"""The online state from the command line: replay writes the odometry, the path and the odom TF; ``vi3 eval`` chains
clips (JSON, TUM) and pools several sequences."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from msg_adapters.diagnostics import diagnostic_array_to_statuses
from msg_adapters.poses import odometry_to_numpy, poses_to_T, tf_message_to_list
from msg_adapters.stamps import stamp_to_ns
from vi3_core.dataset.calib import write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_core.eval.tum import read_tum
from vi3_ros.cli import main as vi3_main

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences


def _read(path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return out


def test_replay_writes_odometry_path_and_tf_in_odom(cache_dir, tmp_path):
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    out = tmp_path / "out.mcap"
    assert vi3_main(["replay", str(asl), "--output", str(out), "--calib", str(calib), "--backbone", "classical",
                     "--no-progress", "--param", "publish_odom_tf=true", "--param", "outputs_in_odom=true"]) == 0
    msgs = _read(out)
    odom, paths = msgs["/vi3_node/odom"], msgs["/vi3_node/path"]
    assert len(odom) == len(paths) >= 2
    assert {(o.header.frame_id, o.child_frame_id) for o in odom} == {("odom", "base_link")}
    tfs = [t for m in msgs["/tf"] for t in tf_message_to_list(m)]
    assert [(p, c) for _, p, c, _ in tfs] == [("odom", "base_link")] * len(odom)
    T_last = odometry_to_numpy(odom[-1])[0]
    np.testing.assert_allclose(tfs[-1][0], T_last, atol=1e-9)
    path_T = poses_to_T([p.pose for p in paths[-1].poses])
    np.testing.assert_allclose(path_T[-1], T_last, atol=1e-9)
    stamps = [stamp_to_ns(p.header.stamp) for p in paths[-1].poses]
    assert stamps == sorted(set(stamps)) and stamps[-1] == stamp_to_ns(odom[-1].header.stamp)
    assert {p.header.frame_id for p in msgs["/vi3_node/poses"]} == {"odom"}
    statuses = [s for m in msgs["/vi3_node/status"] for s in diagnostic_array_to_statuses(m)]
    assert all("online" in s.values for s in statuses if s.values.get("result") == "init")


def test_vi3_eval_chained_json_and_tum(cache_dir, tmp_path, capsys):
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    common = ["eval", str(asl), "--json", "--clips", "sliding", "--max-clips", "2", "--no-progress"]
    assert vi3_main([*common, "--export-tum", str(tmp_path)]) == 0
    obj = json.loads(capsys.readouterr().out)
    chained = obj["chained"]
    assert {"ate_m", "drift_pct", "gravity_err_deg", "resets", "segments", "scale_err_median",
            "independent_scale_err_median", "independent_claimed_outliers"} <= set(chained)
    assert chained["resets"] == 0 and chained["segments"] == 1 and "claimed_outliers" in obj
    assert all(np.isfinite(chained[k]) for k in ("ate_m", "drift_pct", "gravity_err_deg"))
    assert chained["scale_err_median"] is None  # 2 clips: none after the first 3
    assert len(chained["decisions"]) == obj["n_clips"] == 2
    stamps, T = read_tum(tmp_path / "odom_vi3.txt")
    assert len(stamps) == chained["frames"] == 8 * obj["status_counts"]["ok"] and np.all(np.diff(stamps) > 0)
    assert vi3_main([*common, "--independent"]) == 0
    assert "chained" not in json.loads(capsys.readouterr().out)


def test_vi3_eval_scores_the_scale_links_against_the_ground_truth(cache_dir, capsys):
    """Three consecutive clips: the second and third join the window through their scale links, and each link's
    ratio is scored against the ratio of the two clips' own scales on the ground truth (a render's links are good
    to their sigmas); the front end's losses are reported per clip and over the run."""
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    common = ["eval", str(asl), "--clips", "sliding", "--max-clips", "3", "--no-progress"]
    assert vi3_main([*common, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    chained = report["chained"]
    links = chained["link_errors"]
    assert links["scored"] == chained["links"]["accepted"] == 2 and links["per_link_sd"] is None, chained
    assert links["z_median"] < 3.0 and links["within_2sigma"] >= 0.5 and 0.0 < links["sigma_median"] < 0.02, links
    # the front end's losses: each frame counted once (the shared frame by the clip that tracked it)
    assert [c["front_end"]["frames"] for c in report["clips"]] == [8, 7, 7]
    front = report["front_end"]
    assert front["frames"] == 22 and front["starts"] == 1 and front["followed_per_frame"] > 100
    assert 0.0 < sum(front["lost"].values()) < 0.5 and 0.0 <= front["new_lost"] <= 1.0
    assert 1.0 <= front["track_length"] <= 22 and 0.0 <= front["long_tracks"] <= 1.0
    assert vi3_main(common) == 0
    out = capsys.readouterr().out
    assert "scale links against the ground truth: 2 scored" in out and "front end (22 frames, 1 started afresh):" in out


def test_vi3_eval_pools_several_sequences(cache_dir, tmp_path, capsys):
    """Several inputs: each sequence reported, then their clips pooled (JSON "sequences" + "pooled"); plots and TUM
    files are named after the sequences."""
    paths = [cached_sequence(cache_dir, seconds=2.5, seed=seed, with_depth=False) for seed in (1, 3)]
    rc = vi3_main(["eval", *map(str, paths), "--json", "--clips", "sliding", "--max-clips", "2", "--no-progress",
                   "--plot", str(tmp_path / "eval.png"), "--export-tum", str(tmp_path / "tum")])
    obj = json.loads(capsys.readouterr().out)
    assert rc == 0 and [s["n_clips"] for s in obj["sequences"]] == [2, 2]
    names = [s["sequence"] for s in obj["sequences"]]
    assert len(set(names)) == 2 and obj["pooled"]["n_clips"] == 4
    pooled = obj["pooled"]["chained"]
    assert pooled["sequences"] == 2 and pooled["resets"] == 0
    assert pooled["drift_pct_max"] == max(s["chained"]["drift_pct"] for s in obj["sequences"])
    assert pooled["link_errors"]["scored"] == sum(s["chained"]["link_errors"]["scored"] for s in obj["sequences"])
    assert pooled["independent_claimed_outliers"]["count"] == sum(
        s["chained"]["independent_claimed_outliers"]["count"] for s in obj["sequences"])
    assert all((tmp_path / f"eval_{n}.png").is_file() and (tmp_path / "tum" / n / "odom_vi3.txt").is_file()
               for n in names)
