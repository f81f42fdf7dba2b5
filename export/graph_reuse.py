"""A new bundle that keeps another bundle's detector or fusion graphs byte for byte (`pallet6d export
--detector-from`, `--fusion-from`).

Retraining one stage should not change the others: a site has tuned its score threshold on its detector, and a
measured fusion graph is the one that was measured. Yet exporting the same weights again need not give the same
int8 graph (the quantization recipe or the calibration frames may have changed since). The exporter therefore
writes its own graphs as usual and then, for each kept stage whose float graph gives the other bundle's float
outputs (the same network), puts that bundle's files of the stage in place of its own, with their checks from that
bundle's report.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from pallet6d.runtime.bundle import REPORT, BundleError, load_bundle, sha256_file

from .export_inputs import ExportError
from .onnx_io import graph_diff

__all__ = ["take_graphs", "KEEPABLE", "SAME_NETWORK_REL_RMS"]

KEEPABLE = ("detector", "fusion")
# the float graphs of one network differ by float rounding (measured 1e-7 relative RMS); a network trained
# further differs by orders of magnitude more
SAME_NETWORK_REL_RMS = 1e-4


def take_graphs(stage: str, source: Path, out: Path, files: dict, int8_files: dict | None, feeds: list,
                spec_fields: dict, checks: dict) -> dict:
    """Replace the `stage` graphs just written to `out` by `source`'s, in place.

    :param stage: "detector" or "fusion".
    :param files: the new bundle's float graphs by stage; `files[stage]` is overwritten.
    :param int8_files: the int8 graphs by stage, or None (no int8 export); a quantized `int8_files[stage]` is
        overwritten (one that is the float graph stays so).
    :param feeds: `stage` inputs held out from calibration, on which both float graphs must agree.
    :param spec_fields: what the new manifest says of the stage (sizes, names, normalisation): `source`'s must say
        the same.
    :param checks: the new bundle's checks; its entries of `stage` are replaced by `source`'s (returned updated).
    :return: the updated checks, with `<stage>_from` (the source, its files' sha256, the agreement measured).
    :raises ExportError: `source` is not a bundle, lacks a graph the export needs, describes the stage otherwise,
        or its network is another.
    """
    if stage not in KEEPABLE:
        raise ExportError(f"only the {' and '.join(KEEPABLE)} graphs can be kept from another bundle, not {stage!r}")
    flag = f"--{stage}-from {source}"
    try:
        src = load_bundle(source)
    except (BundleError, OSError) as exc:
        raise ExportError(f"{flag}: not a model bundle ({exc})") from None
    theirs = getattr(src.manifest, stage)
    for key, mine in spec_fields.items():
        if getattr(theirs, key) != mine:
            raise ExportError(f"{flag}: its {stage}'s {key} is {getattr(theirs, key)!r}, the exported one's {mine!r}")
    quantized_here = int8_files is not None and int8_files[stage] != files[stage]
    if quantized_here and theirs.file_int8 is None:
        raise ExportError(f"{flag}: it has no int8 {stage} graph to keep; export without --int8")
    agreement = graph_diff(src.graph(stage), files[stage], feeds)
    worst = max(v["rel_rms"] for v in agreement.values())
    if not worst <= SAME_NETWORK_REL_RMS:
        raise ExportError(f"{flag}: its float {stage} graph and the checkpoint's differ by {worst:.2g} relative RMS "
                          f"(limit {SAME_NETWORK_REL_RMS}): another network; merge the checkpoint from that bundle's "
                          f"{stage} (`pallet6d train merge`)")
    shutil.copyfile(src.graph(stage), files[stage])
    kept = {"float": sha256_file(files[stage])}
    if quantized_here:
        shutil.copyfile(src.graph(stage, "int8"), int8_files[stage])
        kept["int8"] = sha256_file(int8_files[stage])
    their_checks = _report_checks(src.root)
    out_checks = dict(checks)
    for group in ("parity", "int8", "weights_int8", "weights_fp16"):
        if isinstance(out_checks.get(group), dict):
            mine = {k: v for k, v in out_checks[group].items() if not k.startswith(stage)}
            out_checks[group] = {**mine, **{k: v for k, v in their_checks.get(group, {}).items()
                                            if k.startswith(stage)}}
    out_checks[f"{stage}_from"] = {"bundle": str(source), "name": src.name, "sha256": kept,
                                   "float_graphs_agree_rel_rms": worst}
    return out_checks


def _report_checks(root: Path) -> dict:
    """The checks of a bundle's report, or {} without a report."""
    path = root / REPORT
    if not path.is_file():
        return {}
    return json.loads(path.read_text(encoding="utf-8")).get("checks", {})
