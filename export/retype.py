"""A bundle with another set of pallet types, its graphs kept byte for byte.

A bundle's graphs do not depend on which pallet types it carries: the pose network predicts the pose of the
bounding-box frame of whatever pallet it sees, and the runtime takes each type's geometry (model points,
symmetries, boards, pockets, ICP starts) from the manifest. A pose network trained on several types can therefore
be given every type it was trained on, or fewer, without exporting its graphs again. This writes a new bundle
folder: every graph copied unchanged, the types' model points written from the simulator's catalogue
(`pallet_types.write_pallet_types`), and the manifest's `pallet_types` and `files`. The report keeps the old
provenance, checks and scores and records the change under `provenance.pallet_types`; re-measure the scores
before shipping (the type choice changes what the estimator poses).

usage: python -m pallet6d.export.retype --bundle models/epal-default --pallet-types epal,eur3 --out /tmp/b
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

from pallet6d.runtime.bundle import MANIFEST, REPORT, load_bundle, sha256_file

from .export_inputs import ExportError, git_commit
from .pallet_types import class_ids_for_types, parse_pallet_types, trained_pallet_types, write_pallet_types

__all__ = ["retype_bundle", "main"]
log = logging.getLogger(__name__)


def _trained_types(report: dict) -> tuple[str, ...] | None:
    """The pallet types the bundle's pose stage was trained on, from its provenance; None when it records none."""
    names = trained_pallet_types((report.get("provenance") or {}).get("training"), "")
    return None if names == ("",) else names


def retype_bundle(src: str | Path, out: str | Path, names: tuple[str, ...], *, command: str = "",
                  allow_untrained: bool = False) -> Path:
    """Write `out`: the bundle `src` carrying the pallet types `names` (module docstring).

    :param names: sim pallet model names; the first is the bundle's first type (a detection's default type).
    :param allow_untrained: also accept types the pose stage was not trained on (or a bundle that does not say).
    :raises ExportError: `out` is not new or empty, a type is unknown or untrained, or the detector's classes
        cannot report the types.
    """
    src, out = Path(src), Path(out)
    if out.exists() and any(out.iterdir()):
        raise ExportError(f"output folder {out} is not empty; choose a new folder")
    bundle = load_bundle(src)
    report = json.loads(json.dumps(bundle.report))
    trained = _trained_types(report)
    untrained = [n for n in names if trained is None or n not in trained]
    if untrained and not allow_untrained:
        said = "records none" if trained is None else f"records {', '.join(trained)}"
        raise ExportError(f"the pose stage of {src} was not trained on {', '.join(untrained)} (its provenance "
                          f"{said}); --allow-untrained to carry them anyway")
    det = bundle.detector
    class_ids = class_ids_for_types(names, tuple(det.classes), det.source == "external")

    manifest = json.loads((bundle.root / MANIFEST).read_text(encoding="utf-8"))
    old_names = [t["name"] for t in manifest["pallet_types"]]
    old_points = {t["points_file"] for t in manifest["pallet_types"]}
    shutil.copytree(src, out, dirs_exist_ok=True, ignore=lambda d, fs: [
        f for f in fs if (Path(d) / f).relative_to(src).as_posix() in old_points])
    try:
        types = write_pallet_types(names, class_ids, out)
        manifest["pallet_types"] = [t.to_dict() for t in types]
        graphs = {f: h for f, h in manifest["files"].items() if f not in old_points}
        manifest["files"] = {**graphs, **{t.points_file: sha256_file(out / t.points_file) for t in types}}
        (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
        report.setdefault("provenance", {})["pallet_types"] = {
            "command": command, "git_commit": git_commit(),
            "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "from": {"bundle": str(src), "pallet_types": old_names},
            "pallet_types": list(names), "trained_on": None if trained is None else list(trained)}
        (out / REPORT).write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        load_bundle(out)   # the runtime must accept what was written
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)   # no half-written bundle
        raise
    log.info("%s: %d pallet types (%s), graphs unchanged", out, len(names), ", ".join(names))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pallet6d.export.retype", description=__doc__.split("\n")[0])
    parser.add_argument("--bundle", required=True, help="the bundle whose graphs are kept")
    parser.add_argument("--pallet-types", required=True,
                        help="comma-separated sim pallet types, the bundle's first type first; 'trained': every type "
                             "the pose stage was trained on, in the order of the bundle's types then its training")
    parser.add_argument("--allow-untrained", action="store_true",
                        help="also carry types the pose stage was not trained on")
    parser.add_argument("--out", required=True, help="the new bundle folder (new or empty)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    command = "python -m pallet6d.export.retype " + shlex.join(sys.argv[1:] if argv is None else argv)
    try:
        names = _names(args.pallet_types, args.bundle)
        retype_bundle(args.bundle, args.out, names, command=command, allow_untrained=args.allow_untrained)
    except (ValueError, OSError) as exc:     # ExportError and BundleError are ValueErrors
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def _names(text: str, src: str) -> tuple[str, ...]:
    """--pallet-types as names; "trained": the bundle's own types first, then the rest of its pose training's."""
    if text.strip() != "trained":
        return parse_pallet_types(text)
    bundle = load_bundle(src)
    trained = _trained_types(bundle.report)
    if trained is None:
        raise ExportError(f"{src} records no pallet types of its pose training; name the types")
    own = tuple(t.name for t in bundle.pallet_types)
    return own + tuple(n for n in trained if n not in own)


if __name__ == "__main__":
    sys.exit(main())
