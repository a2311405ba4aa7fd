"""The cost of an adapter (issue 28, finding 2): a graph of allowed operators whose work explodes is refused by a
static bound before anything runs (render_core/adapters/cost.py), honest adapters pass it, a tensor whose size
cannot be bounded is refused by name, the HTTP upload answers 422 naming the cost, and a run over the per-frame
adapter budget (adapter_budget_ms) refuses its frames with a named error."""

from __future__ import annotations

import json
import time
import tracemalloc

import grpc
import httpx
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.adapters.manifest import AdapterError, AdapterManifest
from render_core.facemodel.open_head import ARKIT_52
from tests.test_service import GrpcStream, next_frame

T = len(ARKIT_52)  # the open head's expressions (the demo avatar's)
S = 4


def _model(nodes, inits, t: int = T, s: int = S) -> bytes:
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("source", TensorProto.FLOAT, ["batch", s])],
                          [helper.make_tensor_value_info("expression", TensorProto.FLOAT, ["batch", t])], inits)
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    onnx.checker.check_model(model)
    return model.SerializeToString()


def _consts(t: int, s: int = S) -> list:
    return [numpy_helper.from_array(np.eye(s, t, dtype=np.float32), "W"),
            numpy_helper.from_array(np.array([0], np.int64), "starts"),
            numpy_helper.from_array(np.array([t], np.int64), "ends"),
            numpy_helper.from_array(np.array([1], np.int64), "axes")]


def bomb(concats: int = 20, t: int = T) -> bytes:
    """source [B, 4] -> MatMul W [4, T] -> ``concats`` x Concat(x, x, axis=1) -> Slice [:, :T] -> expression: each
    Concat doubles the tensor (21 of them: gigabytes per frame from a model of 2 KB)."""
    nodes = [helper.make_node("MatMul", ["source", "W"], ["x0"])]
    nodes += [helper.make_node("Concat", [f"x{i}", f"x{i}"], [f"x{i + 1}"], axis=1) for i in range(concats)]
    nodes.append(helper.make_node("Slice", [f"x{concats}", "starts", "ends", "axes"], ["expression"]))
    return _model(nodes, _consts(t), t)


def honest(t: int = T) -> bytes:
    """MatMul + Slice: what the bomb is without its Concats."""
    return bomb(0, t)


def mlp(hidden: int = 256, s: int = len(ARKIT_52), t: int = T) -> bytes:
    """A two-layer MLP: source [B, S] -> Gemm [S, hidden] -> Relu -> MatMul [hidden, hidden] -> Tanh -> MatMul
    [hidden, T] -> Sigmoid -> expression."""
    rng = np.random.default_rng(0)
    w = [rng.normal(0, 0.1, shape).astype(np.float32) for shape in ((s, hidden), (hidden, hidden), (hidden, t))]
    inits = [numpy_helper.from_array(a, f"W{i}") for i, a in enumerate(w)]
    inits.append(numpy_helper.from_array(np.zeros(hidden, np.float32), "b0"))
    nodes = [helper.make_node("Gemm", ["source", "W0", "b0"], ["h0"]), helper.make_node("Relu", ["h0"], ["a0"]),
             helper.make_node("MatMul", ["a0", "W1"], ["h1"]), helper.make_node("Tanh", ["h1"], ["a1"]),
             helper.make_node("MatMul", ["a1", "W2"], ["h2"]), helper.make_node("Sigmoid", ["h2"], ["expression"])]
    return _model(nodes, inits, t, s)


def data_shaped(t: int = T) -> bytes:
    """A Reshape whose target shape is computed from the input's values (two source values cast to int64)."""
    ints = [numpy_helper.from_array(np.array(v, np.int64), n)
            for n, v in (("c0", [0, 0]), ("c1", [1, 2]), ("flat", [-1]), ("back", [-1, t]))]
    nodes = [helper.make_node("MatMul", ["source", "W"], ["x0"]),
             helper.make_node("Slice", ["source", "c0", "c1"], ["corner"]),
             helper.make_node("Reshape", ["corner", "flat"], ["values"]),
             helper.make_node("Cast", ["values"], ["shape"], to=TensorProto.INT64),
             helper.make_node("Reshape", ["x0", "shape"], ["reshaped"]),
             helper.make_node("Reshape", ["reshaped", "back"], ["expression"])]
    return _model(nodes, _consts(t)[:1] + ints, t)


def manifest(adapter_id: str, names: list[str] = ARKIT_52, face_model: str = "open-head-anny",
             s: int = S) -> AdapterManifest:
    return AdapterManifest(id=adapter_id, source_names=[f"s{i}" for i in range(s)], target_face_model=face_model,
                           target_expression_names=list(names), expression_min=[0.0] * len(names),
                           expression_max=[1.0] * len(names), source_convention="custom")


# -------------------------------------------------------------------------------------------- static bound
def test_the_concat_bomb_is_refused_by_its_cost_before_anything_runs(monkeypatch):
    from render_core.adapters import runtime
    from render_core.adapters.validate import validate_model

    def never(*args, **kwargs):
        raise AssertionError("onnxruntime was given a model whose cost is not bounded")

    monkeypatch.setattr(runtime.AdapterRuntime, "__init__", never)
    data = bomb()
    assert len(data) < 4096
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(AdapterError) as e:
            validate_model(data, manifest("bomb"))
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert e.value.field.startswith("model") and "cost" in str(e.value), str(e.value)
    # the first tensor over the bound is named, with its figure and the limit
    assert "'x11'" in str(e.value) and "6,815,744" in str(e.value) and "4,194,304" in str(e.value), str(e.value)
    assert seconds < 2 and peak < 50 << 20, (seconds, peak)


def test_each_bound_names_its_figure_and_limit():
    from render_core.adapters.cost import adapter_cost

    model = onnx.ModelProto.FromString(bomb(5))
    cost = adapter_cost(model)
    assert cost.batch == 64 and cost.largest == ("x5", 64 * T * 32)
    with pytest.raises(AdapterError, match=r"cost .*'x3'.*MAX_ADAPTER_TENSOR_ELEMENTS"):
        adapter_cost(model, max_tensor_elements=64 * T * 4)
    with pytest.raises(AdapterError, match=r"cost .*bytes.*MAX_ADAPTER_INTERMEDIATE_BYTES"):
        adapter_cost(model, max_intermediate_bytes=cost.intermediate_bytes - 1)
    with pytest.raises(AdapterError, match=r"cost .*multiply-adds.*MAX_ADAPTER_WORK"):
        adapter_cost(model, max_work=cost.work - 1)
    # MatMul work is multiply-adds: 64 x 4 x T for the first node, then the elements each node writes
    assert adapter_cost(onnx.ModelProto.FromString(honest())).work == 64 * S * T + 64 * T


def test_honest_adapters_pass_the_bound_and_are_accepted():
    from render_core.adapters.cost import MAX_ADAPTER_WORK, adapter_cost
    from render_core.adapters.runtime import AdapterRuntime
    from render_core.adapters.validate import validate_model

    validate_model(honest(), manifest("honest"))
    m = manifest("mlp", s=len(ARKIT_52))
    data = mlp()
    validate_model(data, m)
    cost = adapter_cost(onnx.ModelProto.FromString(data))
    assert cost.work < MAX_ADAPTER_WORK // 16, cost  # far from the bound
    expression, _, errors = AdapterRuntime(data, m).run(np.full((3, len(ARKIT_52)), 0.5, np.float32))
    assert expression.shape == (3, T) and errors == [None] * 3


def test_a_tensor_whose_size_cannot_be_bounded_is_refused_by_name():
    from render_core.adapters.validate import validate_model

    with pytest.raises(AdapterError) as e:
        validate_model(data_shaped(), manifest("data-shaped"))
    assert e.value.field == "model" and "cost" in str(e.value) and "'reshaped'" in str(e.value), str(e.value)
    assert "[?, ?]" in str(e.value)


def test_declared_shapes_are_not_trusted():
    """A value-info that claims a small shape for the data-shaped tensor changes nothing: declared shapes are
    dropped before inference."""
    from render_core.adapters.validate import validate_model

    model = onnx.ModelProto.FromString(data_shaped())
    model.graph.value_info.append(helper.make_tensor_value_info("reshaped", TensorProto.FLOAT, ["batch", T]))
    with pytest.raises(AdapterError, match="'reshaped'"):
        validate_model(model.SerializeToString(), manifest("liar"))


def test_a_probe_run_has_a_hard_time_limit():
    """run_raw(limit_s): onnxruntime's terminate flag stops a run that is still going (between nodes)."""
    from render_core.adapters.runtime import AdapterRuntime

    nodes = [helper.make_node("MatMul", ["source", "W"], ["x0"])]
    nodes += [helper.make_node("Sqrt", [f"x{i}"], [f"x{i + 1}"]) for i in range(100)]
    nodes.append(helper.make_node("Slice", ["x100", "starts", "ends", "axes"], ["expression"]))
    wide = 1 << 14
    data = _model(nodes, [numpy_helper.from_array(np.eye(S, wide, dtype=np.float32), "W")] + _consts(T)[1:])
    runtime = AdapterRuntime(data, manifest("slow"))
    source = np.ones((64, S), np.float32)
    start = time.perf_counter()
    runtime.run_raw(source)
    full = time.perf_counter() - start
    start = time.perf_counter()
    with pytest.raises(Exception, match="(?i)terminat"):
        runtime.run_raw(source, limit_s=full / 20)
    assert time.perf_counter() - start < full / 2, full


# ------------------------------------------------------------------------------------------- the service
@pytest.fixture(scope="module")
def http(live_server):
    with httpx.Client(base_url=live_server.http_url, timeout=120, headers=live_server.headers) as client:
        yield client


def put_adapter(http, adapter_id: str, model: bytes, m: AdapterManifest) -> httpx.Response:
    text = json.dumps({**m.to_dict(), "id": adapter_id})
    return http.put(f"/v1/adapters/{adapter_id}", files={"manifest": ("manifest.json", text, "application/json"),
                                                         "model": ("model.onnx", model, "application/octet-stream")})


def test_http_upload_of_the_bomb_is_a_422_naming_the_cost(http):
    r = put_adapter(http, "cost-honest", honest(), manifest("cost-honest"))
    assert r.status_code in (200, 201), r.text
    start = time.perf_counter()
    r = put_adapter(http, "cost-bomb", bomb(), manifest("cost-bomb"))
    assert time.perf_counter() - start < 10
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["field"].startswith("model") and "cost" in error["message"], error
    assert http.get("/v1/adapters/cost-bomb").status_code == 404  # nothing stored
    assert http.delete("/v1/adapters/cost-honest").status_code == 200


def test_a_run_over_the_adapter_budget_refuses_its_frame_by_name(live_server, http, monkeypatch, caplog):
    """The budget set to almost nothing (adapter_budget_ms): every run is over it, so each frame is refused with
    RESOURCE_EXHAUSTED naming the adapter and the budget, the stream goes on, and the adapter is logged once."""
    from service.adapters import ADAPTER_BUDGET_MS

    assert ADAPTER_BUDGET_MS == 20.0 and live_server.engine.adapters.budget_ms == ADAPTER_BUDGET_MS
    demo = http.get(f"/v1/avatars/{live_server.avatar_id}").json()
    names = demo["expression_names"]
    m = manifest("cost-budget", names, demo["face_model"])
    assert put_adapter(http, "cost-budget", honest(len(names)), m).status_code == 201
    monkeypatch.setattr(live_server.engine.adapters, "budget_ms", 1e-9)
    try:
        with caplog.at_level("WARNING", logger="service.adapters"), \
                grpc.insecure_channel(live_server.grpc_target) as channel:
            stream = GrpcStream(pb_grpc.RenderServiceStub(channel), avatar_id=live_server.avatar_id, width=32,
                                height=32, codec=pb.CODEC_PNG, adapter="cost-budget")
            assert stream.next().header.adapter_id == "cost-budget"
            for i in (1, 2):
                stream.send(frame=pb.FrameParams(index=i, coefficients=[0.5] * S))
                reply = stream.next()
                assert reply.WhichOneof("msg") == "error", reply
                assert reply.error.code == pb.RESOURCE_EXHAUSTED and reply.error.field == "adapter"
                assert reply.error.frame_index == i
                assert "'cost-budget'" in reply.error.message and "adapter_budget_ms" in reply.error.message
            stream.close()
        assert caplog.text.count("over the adapter budget") == 1, caplog.text
        monkeypatch.undo()  # the default budget, and the adapter stored again (loaded afresh): it renders
        assert put_adapter(http, "cost-budget", honest(len(names)), m).status_code == 201
        with grpc.insecure_channel(live_server.grpc_target) as channel:
            stream = GrpcStream(pb_grpc.RenderServiceStub(channel), avatar_id=live_server.avatar_id, width=32,
                                height=32, codec=pb.CODEC_PNG, adapter="cost-budget")
            stream.next()
            stream.send(frame=pb.FrameParams(index=1, coefficients=[0.5] * S))
            assert next_frame(stream).index == 1
            stream.close()
    finally:
        http.delete("/v1/adapters/cost-budget")
