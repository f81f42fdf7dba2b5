"""A thin onnxruntime session wrapper: built once, threads set, inputs checked by name.

Intra-op threads = the cores given to the runtime, inter-op 1 (the graphs are chains; a second
pool only competes for the same two cores), all graph optimisations on, sequential execution.
The pool's threads spin while a run is under way (a woken thread starts the next op's share at once, instead
of sleeping between the graph's many small ops) and stop spinning the moment it returns
(`session.force_spinning_stop`): each of the three sessions has its own pool, and a pool that kept spinning
after its graph ran would steal the cores from the next graph and the numpy stages in between (2 threads on
2 cores, one pallet, int8: no spinning 30.5 ms a frame, spinning during runs 26.8 ms, spinning throughout 66 ms;
benchmarks/results/latency-spinning/).

No CPU memory arena and no memory patterns: an arena keeps the largest activations each graph has ever
needed, for good and per session (about 130 MB more resident with 8 pallets in a fusion batch), while without
it a run's activations go back to the C allocator when the run ends, and the three graphs, which run one
after the other, reuse the same freed memory; without patterns each tensor is allocated as it is needed
rather than all of a run's at once, which lowers the peak by a few MB more at the same CPU time
(docs/experiments/latency.md, "Memory").
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .manifest_fields import BundleError

__all__ = ["OnnxModel", "session_options"]

log = logging.getLogger(__name__)


def session_options(threads: int) -> ort.SessionOptions:
    """Session options for the forklift computer: `threads` intra-op threads, 1 inter-op thread."""
    if int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    so.enable_cpu_mem_arena = False
    so.enable_mem_pattern = False
    so.add_session_config_entry("session.intra_op.allow_spinning", "1")
    so.add_session_config_entry("session.force_spinning_stop", "1")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return so


class OnnxModel:
    """One ONNX graph on the CPU execution provider.

    :param path: the .onnx file.
    :param threads: intra-op threads.
    :param expect_inputs: input names the caller will feed; a graph without them raises ValueError.
    :param expect_outputs: output names the caller reads; a graph without them raises ValueError.
    :raises BundleError: onnxruntime cannot load the graph (damaged, or from a newer opset).
    """

    def __init__(self, path: str | Path, threads: int = 2, expect_inputs: tuple[str, ...] = (),
                 expect_outputs: tuple[str, ...] = ()) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"ONNX graph not found: {self.path}")
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=session_options(threads),
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types; a bundle's graph is at fault
            raise BundleError(f"ONNX graph {self.path}: onnxruntime cannot load it: {exc}") from None
        self.inputs = {i.name: i for i in self.session.get_inputs()}
        self.outputs = [o.name for o in self.session.get_outputs()]
        missing_in = [n for n in expect_inputs if n not in self.inputs]
        missing_out = [n for n in expect_outputs if n not in self.outputs]
        if missing_in or missing_out:
            raise ValueError(f"{self.path.name}: graph lacks inputs {missing_in} / outputs {missing_out} "
                             f"(it has inputs {list(self.inputs)}, outputs {self.outputs}); "
                             "the bundle's manifest and its graphs disagree")
        log.debug("loaded %s (%d threads): inputs %s outputs %s", self.path.name, threads,
                  {n: i.shape for n, i in self.inputs.items()}, self.outputs)

    def input_shape(self, name: str) -> list:
        """Declared shape of an input (ints for fixed axes, str/None for dynamic ones)."""
        return list(self.inputs[name].shape)

    def run(self, feeds: dict[str, np.ndarray], outputs: list[str] | None = None) -> dict[str, np.ndarray]:
        """Run the graph; returns {output name: array}."""
        names = outputs or self.outputs
        return dict(zip(names, self.session.run(names, feeds)))
