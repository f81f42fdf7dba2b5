"""A new bundle that keeps another bundle's detector graphs byte for byte (`pallet6d export --detector-from`).

Retraining the pose stage alone should not change the detector a site has tuned its score threshold on, yet
exporting the same detector weights again need not give the same int8 graph (the quantization recipe or the
calibration frames may have changed since). The exporter therefore writes its own graphs as usual and then, when
its float detector graph gives the other bundle's float detector outputs (the same network), puts that bundle's
detector files in place of its own, with their checks from that bundle's report.
"""
from __future__ import annotations

import shutil
from pathlib import Path

from pallet6d.runtime.bundle import REPORT, BundleError, load_bundle, sha256_file

from .export_inputs import ExportError
from .onnx_io import graph_diff

__all__ = ["take_detector_graphs", "SAME_NETWORK_REL_RMS"]

# the float graphs of one network differ by float rounding (measured 1e-7 relative RMS); a network trained
# further differs by orders of magnitude more
SAME_NETWORK_REL_RMS = 1e-4


def take_detector_graphs(source: Path, out: Path, files: dict, int8_files: dict | None, feeds: list,
                         spec_fields: dict, checks: dict) -> dict:
    """Replace the detector graphs just written to `out` by `source`'s, in place.

    :param files: the new bundle's float graphs by stage; `files["detector"]` is overwritten.
    :param int8_files: the int8 graphs by stage, or None (no int8 export); a quantized `int8_files["detector"]` is
        overwritten (one that is the float graph stays so).
    :param feeds: detector inputs held out from calibration, on which both float graphs must agree.
    :param spec_fields: what the new manifest's detector says (input_hw, input_sizes, classes, depth_max_m,
        input_name, output_name): `source`'s must say the same.
    :param checks: the new bundle's checks; its detector entries are replaced by `source`'s (returned updated).
    :return: the updated checks, with `detector_from` (the source, its files' sha256, the agreement measured).
    :raises ExportError: `source` is not a bundle, lacks a graph the export needs, describes its detector
        otherwise, or its detector is another network.
    """
    try:
        src = load_bundle(source)
    except (BundleError, OSError) as exc:
        raise ExportError(f"--detector-from {source}: not a model bundle ({exc})") from None
    theirs = src.manifest.detector
    for key, mine in spec_fields.items():
        if getattr(theirs, key) != mine:
            raise ExportError(f"--detector-from {source}: its detector's {key} is {getattr(theirs, key)!r}, the "
                              f"exported one's {mine!r}")
    if int8_files is not None and theirs.file_int8 is None:
        raise ExportError(f"--detector-from {source}: it has no int8 detector graph to keep; export without --int8")
    agreement = graph_diff(src.graph("detector"), files["detector"], feeds)
    worst = max(v["rel_rms"] for v in agreement.values())
    if not worst <= SAME_NETWORK_REL_RMS:
        raise ExportError(f"--detector-from {source}: its float detector graph and the checkpoint's differ by "
                          f"{worst:.2g} relative RMS (limit {SAME_NETWORK_REL_RMS}): another network; merge the "
                          f"checkpoint with `pallet6d train merge --detector {source}`")
    shutil.copyfile(src.graph("detector"), files["detector"])
    kept = {"float": sha256_file(files["detector"])}
    if int8_files is not None and int8_files["detector"] != files["detector"]:   # quantized here: theirs instead
        shutil.copyfile(src.graph("detector", "int8"), int8_files["detector"])
        kept["int8"] = sha256_file(int8_files["detector"])
    their_checks = _report_checks(src.root)
    out_checks = dict(checks)
    for group in ("parity", "int8", "weights_int8", "weights_fp16"):
        if group in out_checks and isinstance(out_checks[group], dict):
            out_checks[group] = {k: v for k, v in out_checks[group].items() if not k.startswith("detector")}
            out_checks[group].update({k: v for k, v in their_checks.get(group, {}).items() if k.startswith("detector")})
    out_checks["detector_from"] = {"bundle": str(source), "name": src.name, "sha256": kept,
                                   "float_graphs_agree_rel_rms": worst}
    return out_checks


def _report_checks(root: Path) -> dict:
    """The checks of a bundle's report, or {} without a report."""
    import json

    path = root / REPORT
    if not path.is_file():
        return {}
    return json.loads(path.read_text(encoding="utf-8")).get("checks", {})
