"""Torch weights back from a shipped bundle's float ONNX graphs: fine-tune the model that ships.

Training checkpoints live in `runs/`, outside git; the bundle in `models/` is what a later training run or an
integrator retraining on real data actually has. `load_bundle_weights` rebuilds each network's state from
the graph it was exported to and proves it with a parity check against onnxruntime:

- initializers named after a parameter (`head.cls.0.2.weight`) are copied; float16- and int8-stored ones
  (`weights_fp16`, `weights_int8`) come back through their Cast (and scale Mul);
- the exporter folded each BatchNorm into the convolution before it (anonymous `onnx::Conv_*`
  initializers); the node's name is the module's scope (`/rgb/backbone/layer1/layer1.0/conv1/Conv` is
  `rgb.backbone.layer1.0.conv1`), which takes the folded kernel, and its BatchNorm takes the folded bias;
- Linear weights appear transposed in a MatMul, PReLU slopes reshaped to (C, 1, 1);
- a pose head's first convolution (`pose.SplitInputConv1d`) is two Conv nodes, its local columns and its global
  columns (with the bias), joined again; a graph of the older layout has one Conv with the whole weight;
- a pose graph that gives the most confident hypothesis alone (`pose.MostConfidentPose`) has the network's layers
  under their own names, and is checked against the network wrapped the same way.

A folded BatchNorm has lost its statistics, so they are measured again: the per-channel mean and variance
of its input over calibration crops, with its scale and shift chosen so that the network computes exactly
what the graph computes. In training mode the batch statistics then start close to those, as after the
original training (an identity BatchNorm would normalise every channel to unit variance at the first step).
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from pallet6d.runtime.bundle import MANIFEST, Bundle, load_bundle, sha256_file
from pallet6d.runtime.pose_inputs import gather_features

from .calib_data import CalibrationSet, make_calibration_set
from .config import get_config
from .detector import build_detector
from .fusion import build_fusion
from .onnx_io import check_parity, has_grouped_convs, ort_session, run_session
from .pose import MostConfidentPose, SplitInputConv1d, build_pose
from .export_inputs import trained_activation, trained_architecture
from .train_loop import CKPT_FORMAT, load_checkpoint

__all__ = ["BundleWeightsError", "bundle_checkpoint", "detector_activation_of", "detector_architecture_of",
           "graph_activation", "graph_architecture",
           "load_bundle_weights", "pose_inputs"]

log = logging.getLogger(__name__)

_BN = torch.nn.modules.batchnorm._BatchNorm


class BundleWeightsError(ValueError):
    """A bundle's graph cannot be mapped back onto the network (another config, an external detector, ...)."""


def _graph_values(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    """Initializers by the name their consumers use: a float16- or int8-stored weight under its Cast's (and
    scale Mul's) output, a parameter equal to another (the exporter keeps one copy) under its Identity's output."""
    values = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type in ("Cast", "Identity") and node.input and node.input[0] in values:
            values[node.output[0]] = values[node.input[0]].astype(np.float32)
        elif node.op_type == "Mul" and len(node.input) == 2 and all(i in values for i in node.input):
            values[node.output[0]] = (values[node.input[0]] * values[node.input[1]]).astype(np.float32)
    return values


def _module_path(node_name: str) -> str:
    """'/rgb/backbone/layer1/layer1.0/conv1/Conv' -> 'rgb.backbone.layer1.0.conv1' (the exporter names a
    container's child 'parent.index')."""
    parts: list[str] = []
    prev = ""
    for seg in node_name.strip("/").split("/")[:-1]:
        parts.append(seg[len(prev) + 1:] if prev and seg.startswith(prev + ".") else seg)
        prev = seg
    return ".".join(parts)


def _conv_batchnorm_pairs(net: torch.nn.Module, example: tuple[torch.Tensor, ...]) -> dict[str, str]:
    """{conv module path: BatchNorm module path} for each BatchNorm fed directly by a convolution's output."""
    names = {m: n for n, m in net.named_modules()}
    last_out: dict[int, str] = {}
    pairs: dict[str, str] = {}

    def conv_hook(mod, inp, out):
        last_out[id(out)] = names[mod]

    def bn_hook(mod, inp):
        src = last_out.get(id(inp[0]))
        if src is not None:
            pairs[src] = names[mod]

    convs = (torch.nn.Conv1d, torch.nn.Conv2d)
    hooks = [m.register_forward_hook(conv_hook) for m in net.modules() if isinstance(m, convs)]
    hooks += [m.register_forward_pre_hook(bn_hook) for m in net.modules() if isinstance(m, _BN)]
    try:
        with torch.no_grad():
            net.eval()
            net(*example)
    finally:
        for h in hooks:
            h.remove()
    return pairs


def _state_from_graph(net: torch.nn.Module, graph_path: Path,
                      example: tuple[torch.Tensor, ...]) -> tuple[dict, list[str]]:
    """The state dict the graph encodes, with folded BatchNorms as identities carrying the folded bias.

    :return: (state dict, paths of the folded BatchNorms).
    """
    model = onnx.load(str(graph_path))
    values = _graph_values(model)
    state = {k: v.clone() for k, v in net.state_dict().items()}
    done: set[str] = set()

    def put(key: str, value: np.ndarray) -> None:
        if key not in state:
            raise BundleWeightsError(f"{graph_path.name}: the graph has {key!r}, which this network does not")
        want = tuple(state[key].shape)
        if value.size != int(np.prod(want)):
            raise BundleWeightsError(f"{graph_path.name}: {key!r} is {value.shape} in the graph, {want} in the network "
                                     "(another config?)")
        state[key] = torch.from_numpy(np.array(value, dtype=np.float32).reshape(want))   # a writable copy
        done.add(key)

    for name, value in values.items():
        if name in state:
            put(name, value)
    pairs = _conv_batchnorm_pairs(net, example)
    folded: list[str] = []
    split_parts: dict[str, list] = {}
    modules = dict(net.named_modules())
    # by node as well: the exporter shares one initializer among parameters of equal value (named after one
    # of them), and folded convolutions have anonymous ones
    for node in model.graph.node:
        path = _module_path(node.name)
        mod = modules.get(path)
        consts = [values.get(i) for i in node.input]
        if node.op_type == "Conv" and len(node.input) > 1 and consts[1] is not None:
            if not isinstance(mod, (torch.nn.Conv1d, torch.nn.Conv2d)):
                raise BundleWeightsError(f"{graph_path.name}: node {node.name!r} names module {path!r}, which is not "
                                         "a convolution of this network (another config?)")
            if isinstance(mod, SplitInputConv1d) and consts[1].shape[1] != mod.in_channels:
                split_parts.setdefault(path, []).append(consts)   # one of its two convolutions: joined below
                continue
            put(f"{path}.weight", consts[1])
            bias = consts[2] if len(consts) > 2 else None
            bn = pairs.get(path)
            if bn is not None:                           # folded: the BatchNorm becomes x + bias
                eps, c = modules[bn].eps, modules[bn].num_features
                if f"{path}.bias" in state:
                    put(f"{path}.bias", np.zeros(c))
                put(f"{bn}.weight", np.ones(c))
                put(f"{bn}.bias", bias if bias is not None else np.zeros(c))
                put(f"{bn}.running_mean", np.zeros(c))
                put(f"{bn}.running_var", np.full(c, 1.0 - eps))
                folded.append(bn)
            elif bias is not None:
                put(f"{path}.bias", bias)
        elif isinstance(mod, torch.nn.Linear) and node.op_type in ("MatMul", "Gemm", "Add"):
            for i, v in enumerate(consts):
                if v is None:
                    continue
                if node.op_type == "Add":
                    put(f"{path}.bias", v)
                elif i == 1:                              # x @ W.T (MatMul) or Gemm with transB
                    put(f"{path}.weight", v if node.op_type == "Gemm" else v.T)
                elif i == 2:
                    put(f"{path}.bias", v)
        elif isinstance(mod, torch.nn.PReLU) and node.op_type == "PRelu" and consts[1] is not None:
            put(f"{path}.weight", consts[1])
        elif isinstance(mod, torch.nn.LayerNorm) and node.op_type == "LayerNormalization":
            if consts[1] is not None:
                put(f"{path}.weight", consts[1])
            if len(consts) > 2 and consts[2] is not None:
                put(f"{path}.bias", consts[2])
    for path, parts in split_parts.items():
        # the local columns' convolution has no bias, the global columns' one carries the layer's bias
        local = [p for p in parts if len(p) < 3 or p[2] is None]
        glob = [p for p in parts if len(p) > 2 and p[2] is not None]
        if len(local) != 1 or len(glob) != 1:
            raise BundleWeightsError(f"{graph_path.name}: {path!r} is split into {len(parts)} convolutions, not a "
                                     "local and a global one (another config?)")
        put(f"{path}.weight", np.concatenate([local[0][1], glob[0][1]], axis=1))
        put(f"{path}.bias", glob[0][2])
    left = [k for k in state if k not in done and not k.endswith("num_batches_tracked")]
    if left:
        raise BundleWeightsError(f"{graph_path.name}: no weights in the graph for {len(left)} tensors of the network, "
                                 f"e.g. {left[:4]} (another config?)")
    return state, folded


@torch.no_grad()
def _restore_batchnorm_statistics(net: torch.nn.Module, folded: list[str],
                                  batches: list[tuple[torch.Tensor, ...]]) -> None:
    """Give each folded (identity + bias b) BatchNorm the mean m and variance v of its input over `batches`,
    with weight sqrt(v + eps) and bias b + m: the same function in eval mode, realistic statistics in training."""
    modules = dict(net.named_modules())
    sums: dict[str, list] = {p: [0.0, 0.0, 0] for p in folded}

    def hook_for(path: str):
        def hook(mod, inp):
            x = inp[0].double()
            dims = [0] + list(range(2, x.dim()))
            acc = sums[path]
            acc[0] = acc[0] + x.sum(dims)
            acc[1] = acc[1] + (x * x).sum(dims)
            acc[2] += x.numel() // x.shape[1]
        return hook

    hooks = [modules[p].register_forward_pre_hook(hook_for(p)) for p in folded]
    try:
        net.eval()
        for args in batches:
            net(*args)
    finally:
        for h in hooks:
            h.remove()
    for p in folded:
        s, ss, n = sums[p]
        bn = modules[p]
        mean = s / n
        var = torch.clamp(ss / n - mean * mean, min=0.0)
        bn.running_mean.copy_(mean.float())
        bn.running_var.copy_(var.float())
        bn.weight.copy_(torch.sqrt(var + bn.eps).float())
        bn.bias.add_(mean.float())


def _stage_inputs(stage: str, calib: CalibrationSet, bundle: Bundle) -> tuple[tuple, list[tuple], list[str], list[str]]:
    """(parity example, BatchNorm batches, graph input names, output names) of a stage, from `calib`."""
    t = torch.from_numpy
    d, f, q = bundle.detector, bundle.fusion, bundle.pose
    if stage == "detector":
        images = [(t(calib.images[i:i + 4]),) for i in range(0, len(calib.images), 4)]
        return (t(calib.images[:1]),), images, [d.input_name], [d.output_name]
    choose = f.choose_input    # a sampled fusion graph's third input
    arrays = [calib.rgb_crops, calib.depth_crops] + ([calib.choose] if choose else [])
    names = [f.rgb_input, f.depth_input] + ([choose] if choose else [])
    if stage == "fusion":
        crops = [tuple(t(a[i:i + 8]) for a in arrays) for i in range(0, len(calib.rgb_crops), 8)]
        return tuple(t(a[:2]) for a in arrays), crops, names, [f.output_name]
    points, feats = pose_inputs(calib, bundle, 2)
    example = (t(points), t(feats))
    return example, [example], [q.points_input, q.features_input], [q.quat_output, q.trans_output, q.conf_output]


def pose_inputs(calib: CalibrationSet, bundle: Bundle, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pose graph's inputs for the first `count` calibration crops (all: None): points (B, N, 3) and their fused
    features (B, N, C) from the bundle's own fusion graph."""
    f = bundle.fusion
    names = [f.rgb_input, f.depth_input] + ([f.choose_input] if f.choose_input else [])
    arrays = [a[:count] for a in [calib.rgb_crops, calib.depth_crops] + ([calib.choose] if f.choose_input else [])]
    sess = ort_session(bundle.graph("fusion", "fp32"), threads=2)
    feats = np.concatenate([run_session(sess, {n: a[i:i + 8] for n, a in zip(names, arrays)})[f.output_name]
                            for i in range(0, len(arrays[0]), 8)])
    if not f.choose_input:
        feats = gather_features(feats, calib.choose[:count])
    return calib.points[:count].astype(np.float32), feats.astype(np.float32)


def graph_activation(graph_path: Path) -> str:
    """The activation of one of our detector graphs: "relu" where it has Relu nodes, else YOLOv8's "silu"."""
    return "relu" if any(n.op_type == "Relu" for n in onnx.load(str(graph_path)).graph.node) else "silu"


def graph_architecture(graph_path: Path) -> str:
    """The architecture of one of our detector graphs: "yolox-nano" where it has grouped (depthwise)
    convolutions, else "yolov8"."""
    return "yolox-nano" if has_grouped_convs(graph_path) else "yolov8"


def detector_architecture_of(path: str | Path | None) -> str:
    """The architecture of the detector in `path` (a bundle: its graph's; a checkpoint: its record); "yolov8"
    for None. :raises ValueError: not a bundle or checkpoint, or an unknown recorded architecture."""
    if path is None:
        return "yolov8"
    if Path(path).is_dir():
        return graph_architecture(_read_bundle(path).graph("detector", "fp32"))
    return trained_architecture(load_checkpoint(path))


def detector_activation_of(path: str | Path | None) -> str:
    """The activation of the detector in `path` (a bundle: its graph's; a checkpoint: its record); "silu" for
    None. :raises ValueError: not a bundle or checkpoint, or a checkpoint that records an unknown activation."""
    if path is None:
        return "silu"
    if Path(path).is_dir():
        return graph_activation(_read_bundle(path).graph("detector", "fp32"))
    return trained_activation(load_checkpoint(path))


def _read_bundle(bundle_dir: str | Path) -> Bundle:
    try:
        return load_bundle(bundle_dir)
    except ValueError as exc:
        raise BundleWeightsError(f"--init {bundle_dir}: {exc}") from None


def load_bundle_weights(bundle_dir: str | Path, nets: dict[str, torch.nn.Module], calib_frames: int = 8,
                        seed: int = 0, bundle: Bundle | None = None, calib: CalibrationSet | None = None) -> dict:
    """Load `nets` ({"detector" | "fusion" | "pose": network}) from the bundle's float graphs.

    :param bundle: the bundle already loaded from `bundle_dir`, if it is (else it is loaded here).
    :param calib: the calibration inputs for the parity checks and BatchNorm statistics, if the caller has them (else
        `calib_frames` frames of the bundle's config, seeded by `seed`).
    :return: what to record of it: the bundle's path, name, config, graph sha256s, the parity checks and the
        bundle's record of how each loaded stage was trained.
    :raises BundleWeightsError: not a bundle, a graph the networks cannot take (another config, an
        external detector), or weights that do not reproduce the graph.
    """
    root = Path(bundle_dir)
    bundle = bundle or _read_bundle(root)
    if bundle.detector.source != "pallet6d" and "detector" in nets:
        raise BundleWeightsError(f"--init {root}: its detector is an external graph, not one of ours")
    cfg = get_config(bundle.config)
    cfg = cfg.replace(detector=dataclasses.replace(cfg.detector, input_hw=tuple(bundle.detector.input_hw),
                                                   classes=tuple(bundle.detector.classes),
                                                   depth_max_m=bundle.detector.depth_max_m))
    calib = calib or make_calibration_set(cfg, frames=calib_frames, seed=seed)
    record: dict = {"bundle": str(root), "name": bundle.name, "config": bundle.config, "graphs": {}, "parity": {}}
    for stage, net in nets.items():
        graph = bundle.graph(stage, "fp32")
        example, batches, in_names, out_names = _stage_inputs(stage, calib, bundle)
        device = next(net.parameters()).device
        net.cpu()                                        # in place: an optimizer's references stay valid
        # a detector of another activation than the graph's (a ReLU detector started from a SiLU one) reads the
        # weights through a twin of the graph's, which must reproduce the graph; then takes them (same layers)
        reader = net
        if stage == "detector" and (act := graph_activation(graph)) != net.cfg.activation:
            reader = build_detector(dataclasses.replace(net.cfg, activation=act))
            record["activation"] = {"graph": act, "network": net.cfg.activation}
        try:
            state, folded = _state_from_graph(reader, graph, example)
            reader.load_state_dict(state)
            _restore_batchnorm_statistics(reader, folded, batches)
            graph_net = MostConfidentPose(reader) if stage == "pose" and bundle.pose.hypotheses == "most_confident" \
                else reader
            record["parity"][stage] = check_parity(graph_net, example, graph, in_names, out_names)
            if reader is not net:
                net.load_state_dict(reader.state_dict())
        except RuntimeError as exc:
            raise BundleWeightsError(f"--init {root}: the weights read back from {graph.name} do not reproduce it: "
                                     f"{exc}") from None
        finally:
            net.to(device)
        record["graphs"][stage] = {"file": graph.name, "sha256": sha256_file(graph),
                                   "batchnorms_restored": len(folded)}
        log.info("%s: weights from %s (%d BatchNorms given statistics again), parity ok", stage, graph, len(folded))
    record["sha256"] = sha256_file(bundle.root / MANIFEST)
    trained = bundle.provenance.get("training") or {}
    # by the bundle's training stages: "pose" covers the fusion and pose networks (one record, not two copies)
    record["training"] = {s: trained.get(s) for s in {"pose" if stage == "fusion" else stage for stage in nets}}
    return record


def bundle_checkpoint(bundle_dir: str | Path, stage: str) -> dict:
    """A bundle's detector ("detector") or pose stage ("pose": fusion + pose networks) as a training checkpoint,
    for `pallet6d train merge` beside a newly trained other stage. Its provenance is the bundle's record of how
    that stage was trained, with the read-back check and the bundle's detector input size.

    :raises BundleWeightsError: as `load_bundle_weights`, or an unknown stage.
    """
    bundle = _read_bundle(bundle_dir)
    cfg = get_config(bundle.config)
    if stage == "detector":
        det = bundle.detector
        nets = {"detector": build_detector(dataclasses.replace(
            cfg.detector, input_hw=tuple(det.input_hw), classes=tuple(det.classes), depth_max_m=det.depth_max_m,
            activation=graph_activation(bundle.graph("detector", "fp32")),
            architecture=graph_architecture(bundle.graph("detector", "fp32"))))}
    elif stage == "pose":
        nets = {"fusion": build_fusion(cfg.fusion), "pose": build_pose(cfg.pose, cfg.fusion.feature_dim)}
    else:
        raise BundleWeightsError(f"stage must be 'detector' or 'pose', got {stage!r}")
    record = load_bundle_weights(bundle_dir, nets, bundle=bundle)
    trained = bundle.provenance.get("training") or {}
    before = dict(trained.get(stage) or {})
    provenance = {**before, "stage": stage, "config": bundle.config, "read_back_from_bundle": record}
    if stage == "detector":
        provenance["input_hw"] = list(bundle.detector.input_hw)
        provenance["input_sizes"] = [list(hw) for hw in bundle.detector.input_sizes]
        provenance["classes"] = list(bundle.detector.classes)
        provenance["depth_max_m"] = bundle.detector.depth_max_m
        provenance["activation"] = nets["detector"].cfg.activation
        provenance["architecture"] = nets["detector"].cfg.architecture
    return {"format": CKPT_FORMAT, "format_version": 1, "stage": stage, "config": bundle.config,
            "epoch": before.get("epoch"), "val": before.get("val"), "provenance": provenance,
            **{k: net.state_dict() for k, net in nets.items()}}
