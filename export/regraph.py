"""A bundle's pose graph exported again from its own weights, by the current network code.

How the pose network computes can change without its weights changing (its heads meet the global feature once
per pallet instead of once per point: `pose.SplitInputConv1d`; the graph gives the most confident hypothesis alone:
`pose.MostConfidentPose`). This writes a new bundle folder: every file of the old one copied unchanged except
`pose.onnx`, whose weights are read back from the old graph (`bundle_weights`), exported again, stored as before
(int8 per output channel, float16 or float32) and compared with the old graph on calibration inputs (an old graph
that gives every point's hypothesis is compared at its most confident point), and the manifest's
`pose.hypotheses`. The report keeps the old provenance, checks and scores and records the re-export under
`provenance.pose_graph`; re-measure the scores before shipping.

usage: python -m pallet6d.export.regraph --bundle models/epal-default --out /tmp/epal-default
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import shlex
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

from pallet6d.runtime.bundle import MANIFEST, REPORT, load_bundle, sha256_file

from .bundle_export import FLOAT_WEIGHTS
from .bundle_weights import load_bundle_weights, pose_inputs
from .calib_data import make_calibration_set
from .config import get_config
from .export_inputs import ExportError, git_commit
from .flops import count_gflops
from .onnx_io import check_parity, export_graph, graph_diff
from .pose import MostConfidentPose, build_pose

__all__ = ["regraph_pose", "main"]
log = logging.getLogger(__name__)


def _storage(report: dict) -> str:
    """How the old pose graph stored its weights: "int8", "fp16" or "fp32"."""
    checks = report.get("checks") or {}
    return next((s for s in ("int8", "fp16") if "pose" in (checks.get(f"weights_{s}") or {})), "fp32")


def regraph_pose(src: str | Path, out: str | Path, *, seed: int = 0, frames: int = 8, command: str = "") -> Path:
    """Write `out`: the bundle `src` with its pose graph exported again from its weights (module docstring).

    :raises ExportError: `out` is not new or empty, the bundle's pose graph cannot be read back, or the new
        graph's outputs differ from the old one's by more than its weight storage allows.
    """
    src, out = Path(src), Path(out)
    if out.exists() and any(out.iterdir()):
        raise ExportError(f"output folder {out} is not empty; choose a new folder")
    bundle = load_bundle(src)
    if "int8" in bundle.precision and bundle.graph("pose", "int8") != bundle.graph("pose", "fp32"):
        raise ExportError(f"{src}: its pose stage has a separate int8 graph; only a float pose graph is re-exported")
    report = json.loads(json.dumps(bundle.report))   # a copy: report.json, or a version-1 manifest's own
    cfg = get_config(bundle.config)
    net = build_pose(cfg.pose, bundle.fusion.feature_dim).eval()
    calib = make_calibration_set(cfg, frames=frames, seed=seed)
    read_back = load_bundle_weights(src, {"pose": net}, bundle=bundle, calib=calib)
    points, feats = pose_inputs(calib, bundle)

    shutil.copytree(src, out, dirs_exist_ok=True)
    try:
        _write_pose_graph(bundle, report, net, read_back, out, points, feats, seed, command)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)   # no half-written bundle
        raise
    return out


def _write_pose_graph(bundle, report: dict, net: torch.nn.Module, read_back: dict, out: Path, points: np.ndarray,
                      feats: np.ndarray, seed: int, command: str) -> None:
    q = bundle.pose
    in_names, out_names = [q.points_input, q.features_input], [q.quat_output, q.trans_output, q.conf_output]
    old_graph = bundle.graph("pose", "fp32")
    new_graph = out / old_graph.relative_to(bundle.root)
    example = (torch.from_numpy(points[:2]), torch.from_numpy(feats[:2]))
    graph_net = MostConfidentPose(net)
    export_graph(graph_net, example, new_graph, in_names, out_names, {k: {0: "batch"} for k in in_names + out_names})
    parity = check_parity(graph_net, example, new_graph, in_names, out_names)
    storage = _storage(report)
    feeds = [{q.points_input: points[i:i + 4], q.features_input: feats[i:i + 4]} for i in range(0, len(points), 4)]
    stored_check = None
    if storage != "fp32":
        write, limits = FLOAT_WEIGHTS[storage]
        small = new_graph.with_suffix(".stored.onnx")
        stored = write(new_graph, small)
        stored_check = {**stored.to_dict(), "vs_fp32_weights": graph_diff(new_graph, small, feeds),
                        "limit_rel_rms": limits["pose"]}
        small.replace(new_graph)
    vs_old = _diff_to_old(old_graph, new_graph, feeds, q)
    limit = FLOAT_WEIGHTS[storage][1].get("pose", 1e-4)
    worst = max(v["rel_rms"] for v in vs_old.values())
    if not worst <= limit:
        raise ExportError(f"the re-exported pose graph differs from the old one by {worst:.2g} relative RMS "
                          f"(limit {limit} for {storage} weights)")

    manifest = json.loads((bundle.root / MANIFEST).read_text(encoding="utf-8"))
    rel = new_graph.relative_to(out).as_posix()
    manifest["files"][rel] = sha256_file(new_graph)
    manifest["pose"]["hypotheses"] = "most_confident"
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    checks = report.setdefault("checks", {})
    checks.setdefault("parity", {})["pose"] = parity
    checks.setdefault("gflops", {})["pose_per_pallet"] = round(count_gflops(new_graph), 3)
    if stored_check is not None:
        checks.setdefault(f"weights_{storage}", {})["pose"] = stored_check
    report.setdefault("provenance", {})["pose_graph"] = {
        "command": command, "seed": seed, "git_commit": git_commit(),
        "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "from": {"bundle": str(read_back["bundle"]), "file": rel, "sha256": read_back["graphs"]["pose"]["sha256"]},
        "read_back_parity": read_back["parity"]["pose"], "vs_previous_graph": vs_old}
    (out / REPORT).write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    load_bundle(out)   # the runtime must accept what was written
    log.info("%s: pose graph re-exported (%s weights), vs the old graph: worst relative RMS %.2g", out, storage, worst)


def _diff_to_old(old_graph: Path, new_graph: Path, feeds: list[dict[str, np.ndarray]], q) -> dict:
    """Per output, how the new graph's outputs differ from the old one's (`onnx_io.graph_diff`); an old graph that
    gives every point's hypothesis (`q.hypotheses` "per_point") is read at its most confident point, with the point
    added to its offset, as the runtime reads it."""
    def most_confident(old: dict, feed: dict) -> dict:
        conf = old[q.conf_output]
        idx, rows = conf.argmax(1), np.arange(len(conf))
        return {q.quat_output: old[q.quat_output][rows, idx], q.conf_output: conf[rows, idx],
                q.trans_output: feed[q.points_input][rows, idx] + old[q.trans_output][rows, idx]}

    return graph_diff(old_graph, new_graph, feeds, most_confident if q.hypotheses == "per_point" else None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pallet6d.export.regraph", description=__doc__.split("\n")[0])
    parser.add_argument("--bundle", required=True, help="the bundle whose pose graph is re-exported")
    parser.add_argument("--out", required=True, help="the new bundle folder (new or empty)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the calibration inputs the graphs are compared on")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    command = "python -m pallet6d.export.regraph " + shlex.join(sys.argv[1:] if argv is None else argv)
    try:
        regraph_pose(args.bundle, args.out, seed=args.seed, command=command)
    except (ValueError, OSError) as exc:     # ExportError and BundleWeightsError are ValueErrors
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
