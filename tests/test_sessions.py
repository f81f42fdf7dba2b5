"""The onnxruntime session wrapper: options for two shared cores, checked inputs and outputs."""
from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from pallet6d.runtime.manifest_fields import BundleError
from pallet6d.runtime.sessions import OnnxModel, session_options


def _relu_graph(path):
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["batch", 4])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["batch", 4])
    model = helper.make_model(helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "relu", [x], [y]),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, path)
    return path


def test_pool_spins_only_while_a_run_is_under_way():
    # a pool left spinning after its run takes the cores from the next graph and the numpy stages
    so = session_options(2)
    assert so.intra_op_num_threads == 2 and so.inter_op_num_threads == 1
    assert so.get_session_config_entry("session.intra_op.allow_spinning") == "1"
    assert so.get_session_config_entry("session.force_spinning_stop") == "1"
    assert so.get_session_config_entry("session.inter_op.allow_spinning") == "0"
    assert not so.enable_cpu_mem_arena


@pytest.mark.parametrize("threads", [0, -1])
def test_threads_below_one_refused(threads):
    with pytest.raises(ValueError, match="threads must be >= 1"):
        session_options(threads)


def test_model_runs_and_checks_names(tmp_path):
    path = _relu_graph(tmp_path / "relu.onnx")
    model = OnnxModel(path, threads=2, expect_inputs=("x",), expect_outputs=("y",))
    out = model.run({"x": np.array([[-1.0, 0.5, 2.0, -3.0]], np.float32)})
    np.testing.assert_array_equal(out["y"], [[0.0, 0.5, 2.0, 0.0]])
    with pytest.raises(ValueError, match="graph lacks inputs"):
        OnnxModel(path, expect_inputs=("images",))


def test_damaged_graph_is_a_bundle_error(tmp_path):
    path = tmp_path / "bad.onnx"
    path.write_bytes(b"not a graph")
    with pytest.raises(BundleError, match="onnxruntime cannot load it"):
        OnnxModel(path)
