"""DeMoN's released weights: the checkpoint reader against TensorFlow's, the converter, each layer
kind and the whole v1 graph against TensorFlow (tests/tf_demon_graph.py), and a job on DeMoN's
HDF5 test files with the converted weights.

Needs TensorFlow (``pip install tensorflow-cpu``; CI installs it): the checkpoints are written by
TensorFlow itself under the names and shapes of DeMoN's v1 graph (tests/data/demon_v1_variables.txt).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from demon_lab.nets import DeMoN
from demon_lab.nets.blocks import Conv, ConvPair, UpConv
from demon_lab.tools import convert
from demon_lab.tools.tf_checkpoint import CheckpointFormatError, CheckpointReader

pytestmark = pytest.mark.slow  # TensorFlow's import and graphs: the slow tier

tf = None
"""TensorFlow, imported when the first test of this module runs (collecting the fast tier imports nothing)."""


@pytest.fixture(scope="module", autouse=True)
def tensorflow():
    global tf
    tf = pytest.importorskip("tensorflow", reason="needs TensorFlow to write checkpoints and run its ops "
                                                  "(pip install tensorflow-cpu; CI installs it)")
    return tf

HERE = Path(__file__).resolve().parent
VARIABLES = HERE / "data" / "demon_v1_variables.txt"


def demon_variables() -> dict[str, tuple[int, ...]]:
    shapes = {}
    for line in VARIABLES.read_text().splitlines():
        if line.startswith("net"):
            name, rest = line.split(None, 1)
            shapes[name] = tuple(int(x) for x in re.findall(r"\d+", rest.split("]")[0]))
    return shapes


def random_values(shapes: dict[str, tuple[int, ...]], seed: int = 0) -> dict[str, np.ndarray]:
    """He-scaled kernels and small biases: activations of a sane size through the whole chain."""
    rng = np.random.default_rng(seed)
    values = {}
    for name, shape in shapes.items():
        fan_in = int(np.prod(shape[:-1])) if len(shape) > 1 else 1
        if name.endswith("upconv/kernel"):
            fan_in = shape[0] * shape[1] * shape[3] // 4
        scale = np.sqrt(2.0 / fan_in) if len(shape) > 1 else 0.01
        values[name] = (rng.standard_normal(shape) * scale).astype(np.float32)
    return values


def write_checkpoint(prefix: Path, values: dict[str, np.ndarray]) -> Path:
    """A TensorFlow checkpoint (V2, ``tf.compat.v1.train.Saver``) holding ``values`` by name."""
    graph = tf.Graph()
    with graph.as_default():
        variables = {name: tf.compat.v1.Variable(v, name=f"v{i}") for i, (name, v) in enumerate(values.items())}
        saver = tf.compat.v1.train.Saver(var_list=variables)
        with tf.compat.v1.Session(graph=graph) as session:
            session.run(tf.compat.v1.global_variables_initializer())
            saver.save(session, str(prefix), write_meta_graph=False)
    return prefix


@pytest.fixture(scope="module")
def released(tmp_path_factory):
    """DeMoN's v1 graph's 242 variables (random values) plus an optimiser slot and a step counter,
    written by TensorFlow, and the converted file."""
    tmp = tmp_path_factory.mktemp("released")
    values = random_values(demon_variables())
    extra = {"global_step": np.int64(1234), "netDM1/motion_fc3/bias/Adam": np.zeros(7, np.float32)}
    prefix = write_checkpoint(tmp / "demon_original", {**values, **extra})
    out = tmp / "demon_original.pt"
    assert convert.main([str(prefix), str(out)]) == 0
    return {"prefix": prefix, "values": values, "out": out}


def test_the_reader_reads_what_tensorflow_reads(tmp_path):
    rng = np.random.default_rng(3)
    values = {f"scope{i % 7}/layer{i}/kernel": rng.standard_normal((i % 5 + 1, 3)).astype(np.float32)
              for i in range(300)}  # more entries than one index block holds
    values.update({"step": np.int64(-5), "half": np.float16([1.5, -2]), "ints": np.arange(6, dtype=np.int32),
                   "scalar": np.float32(2.5), "f64": rng.standard_normal((2, 2, 2))})
    prefix = write_checkpoint(tmp_path / "model", values)
    ours, theirs = CheckpointReader(prefix), tf.train.load_checkpoint(str(prefix))
    shapes = theirs.get_variable_to_shape_map()
    assert set(ours.entries) == set(shapes) == set(values)
    for name in values:
        assert list(ours.entries[name].shape) == shapes[name]
        a, b = ours.read(name), theirs.get_tensor(name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    # the prefix, the index or a data shard name the same checkpoint
    for path in (f"{prefix}.index", f"{prefix}.data-00000-of-00001"):
        assert set(CheckpointReader(path).entries) == set(values)
    # a changed byte is caught by the tensor's CRC32C
    data = Path(f"{prefix}.data-00000-of-00001")
    raw = bytearray(data.read_bytes())
    entry = ours.entries["scope3/layer10/kernel"]
    raw[entry.offset + 1] ^= 0x40
    data.write_bytes(bytes(raw))
    with pytest.raises(CheckpointFormatError, match="checksum mismatch in scope3/layer10/kernel"):
        CheckpointReader(prefix).read("scope3/layer10/kernel")


def test_conversion_maps_every_variable_and_loads_strictly(released, capsys):
    state = torch.load(released["out"], weights_only=True)
    chain = DeMoN("v1")
    assert list(state) == list(chain.state_dict())  # exactly the state-dict keys
    chain.load_state_dict(state, strict=True)
    by_key = {v.key: v for v in convert.graph_variables(chain)}
    assert sorted(v.name for v in by_key.values()) == sorted(demon_variables())
    for key, tensor in state.items():
        tf_value = released["values"][by_key[key].name]
        module = chain.get_submodule(key.rsplit(".", 1)[0])
        if isinstance(module, torch.nn.ConvTranspose2d) and key.endswith("weight"):
            expected = tf_value.transpose(3, 2, 0, 1)  # [kh, kw, out, in] -> [in, out, kh, kw]
        elif isinstance(module, torch.nn.Conv2d) and key.endswith("weight"):
            expected = tf_value.transpose(3, 2, 0, 1)  # [kh, kw, in, out] -> [out, in, kh, kw]
        elif isinstance(module, torch.nn.Linear) and key.endswith("weight"):
            expected = tf_value.T
        else:
            expected = tf_value
        assert tensor.dtype == torch.float32 and np.array_equal(tensor.numpy(), expected), key
    assert sum(t.numel() for t in state.values()) == 45_753_883


def test_conversion_counts_what_it_skips(released, tmp_path, capsys):
    out = tmp_path / "again.pt"
    assert convert.main([str(released["prefix"]), str(out)]) == 0
    printed = capsys.readouterr().out
    assert "converted 242 tensors (45,753,883 parameters)" in printed
    assert "skipped 2 variables" in printed and "global_step" in printed
    assert out.read_bytes() == released["out"].read_bytes()


def _tf_graph(values):
    from tf_demon_graph import Graph

    return Graph(values)


def _load(module, values, names):
    """TensorFlow-layout arrays into ``module``'s parameters (``names``: param -> TF name)."""
    with torch.no_grad():
        for param, name in names.items():
            sub, _, leaf = param.rpartition(".")
            target = module.get_submodule(sub) if sub else module
            getattr(target, leaf).copy_(convert.to_torch(values[name], target, leaf))


def _close(ours: torch.Tensor, theirs, tol=1e-5):
    theirs = np.asarray(theirs, dtype=np.float64)
    scale = max(1.0, float(np.abs(theirs).max()))
    assert np.abs(ours.detach().double().numpy() - theirs).max() <= tol * scale


def test_a_plain_conv_layer_is_tensorflows():
    rng = np.random.default_rng(5)
    values = {"c/kernel": rng.standard_normal((3, 3, 4, 8)).astype(np.float32),
              "c/bias": rng.standard_normal(8).astype(np.float32)}
    x = rng.standard_normal((2, 12, 16, 4)).astype(np.float32)  # NHWC, even sides, stride 2
    layer = Conv(4, 8, (3, 3), (2, 2), "v1")
    _load(layer, values, {"conv.weight": "c/kernel", "conv.bias": "c/bias"})
    theirs = _tf_graph(values).conv(tf.constant(x), "c", (3, 3), (2, 2))
    _close(layer(torch.from_numpy(x).permute(0, 3, 1, 2)), np.transpose(theirs, (0, 3, 1, 2)))


def test_a_split_conv_layer_is_tensorflows():
    rng = np.random.default_rng(6)
    values = {"conv1y/kernel": rng.standard_normal((9, 1, 6, 5)).astype(np.float32),
              "conv1y/bias": rng.standard_normal(5).astype(np.float32),
              "conv1x/kernel": rng.standard_normal((1, 9, 5, 7)).astype(np.float32),
              "conv1x/bias": rng.standard_normal(7).astype(np.float32)}
    x = rng.standard_normal((1, 32, 48, 6)).astype(np.float32)
    layer = ConvPair(6, (5, 7), 9, 2, "v1")
    _load(layer, values, {"y.conv.weight": "conv1y/kernel", "y.conv.bias": "conv1y/bias",
                          "x.conv.weight": "conv1x/kernel", "x.conv.bias": "conv1x/bias"})
    theirs = _tf_graph(values).convrelu2(tf.constant(x), "conv1", 9, 2)
    _close(layer(torch.from_numpy(x).permute(0, 3, 1, 2)), np.transpose(theirs, (0, 3, 1, 2)))


@pytest.mark.parametrize("kind", ["refine", "upsample_prediction"])
def test_a_transposed_conv_layer_is_tensorflows(kind):
    rng = np.random.default_rng(7)
    """Both of DeMoN's up-convolutions: ``_refine_caffe_padding`` (VALID, leaky ReLU, cropped by
    one pixel) and ``_upsample_prediction`` ('same', linear)."""
    values = {"r/upconv/kernel": rng.standard_normal((4, 4, 3, 5)).astype(np.float32),  # [kh, kw, out, in]
              "r/upconv/bias": rng.standard_normal(3).astype(np.float32)}
    x = rng.standard_normal((2, 6, 8, 5)).astype(np.float32)
    layer = UpConv(5, 3, relu=kind == "refine")
    _load(layer, values, {"deconv.weight": "r/upconv/kernel", "deconv.bias": "r/upconv/bias"})
    graph = _tf_graph(values)
    if kind == "refine":
        theirs = graph.refine(tf.constant(x), "r", tf.zeros((2, 12, 16, 3)))[..., :3]
    else:
        theirs = graph.upsample_prediction(tf.constant(x), "r")
    _close(layer(torch.from_numpy(x).permute(0, 3, 1, 2)), np.transpose(theirs, (0, 3, 1, 2)))


def test_the_motion_head_dense_layers_are_tensorflows():
    """motion_fc1 reads motion_conv1 flattened in C, H, W order, as DeMoN's NCHW flatten."""
    rng = np.random.default_rng(8)
    from demon_lab.nets.depth_motion_net import _linear

    c, h, w = 4, 3, 5
    values = {"fc1/kernel": rng.standard_normal((c * h * w, 6)).astype(np.float32),
              "fc1/bias": rng.standard_normal(6).astype(np.float32),
              "fc2/kernel": rng.standard_normal((6, 7)).astype(np.float32),
              "fc2/bias": rng.standard_normal(7).astype(np.float32)}
    features = rng.standard_normal((2, h, w, c)).astype(np.float32)  # NHWC, as the graph's motion_conv1
    fc1, fc2 = _linear(c * h * w, 6), _linear(6, 7)
    _load(fc1, values, {"weight": "fc1/kernel", "bias": "fc1/bias"})
    _load(fc2, values, {"weight": "fc2/kernel", "bias": "fc2/bias"})
    graph = _tf_graph(values)
    flat = tf.reshape(tf.transpose(tf.constant(features), [0, 3, 1, 2]), [2, -1])
    theirs = graph.dense(graph.dense(flat, "fc1"), "fc2", act=False)
    from demon_lab.nets.blocks import lrelu

    ours = fc2(lrelu(fc1(torch.from_numpy(features).permute(0, 3, 1, 2).flatten(1))))
    _close(ours, theirs)


def test_the_converted_chain_computes_demons_graph(released):
    """DeMoN(compat="demon_original") with the converted weights against the v1 graph transcribed
    into TensorFlow: the bootstrap pass end to end (flow1, warp2d, dm1), then each iterative net and
    the refinement net on the graph's own inputs of that pass (with random weights the unclipped
    triangulated depth is ill-conditioned, and the float32 rounding of the two implementations
    would be amplified from pass to pass)."""
    from demon_lab.nets.chain import Prediction, depth_motion_net_inputs, flow_net_inputs

    rng = np.random.default_rng(1)
    image1, image2 = (torch.from_numpy(rng.uniform(-0.5, 0.5, (1, 3, 192, 256)).astype(np.float32)) for _ in "12")
    image2_2 = torch.nn.functional.avg_pool2d(image2, 4)
    K = torch.tensor([[0.89115971, 1.18821287, 0.5, 0.5]])
    nhwc = lambda x: x.permute(0, 2, 3, 1).numpy()  # noqa: E731
    nchw = lambda x: torch.from_numpy(np.ascontiguousarray(np.transpose(np.asarray(x), (0, 3, 1, 2))))  # noqa: E731
    passes, refined = _tf_graph(released["values"]).run(nhwc(torch.cat([image1, image2], 1)), nhwc(image2_2))
    chain = DeMoN("v1", compat="demon_original")
    chain.load_state_dict(torch.load(released["out"], weights_only=True))
    chain.eval()
    with torch.no_grad():
        out = chain(image1, image2, K, iterations=3)
        first = out.passes[0]
        theirs = passes[0]
        _close(first.flow, nchw(theirs["flowconf2"][..., :2]), 1e-4)
        _close(first.conf, nchw(theirs["flowconf2"][..., 2:]), 1e-4)
        _close(first.flow5, nchw(theirs["flowconf5"][..., :2]), 1e-4)
        _close(first.inv_depth, nchw(theirs["depth2"]), 1e-4)
        _close(first.normals, nchw(theirs["normal2"]), 1e-4)
        _close(first.motion, np.concatenate([theirs["rotation"], theirs["translation"]], 1), 1e-4)
        pair = torch.cat([image1, image2], 1)
        for k in range(1, 4):
            prev, now = passes[k - 1], passes[k]
            prev_motion = torch.from_numpy(np.concatenate([prev["rotation"], prev["translation"]], 1))
            extra = flow_net_inputs(image2_2, nchw(prev["depth2"]), nchw(prev["normal2"]), prev_motion, K,
                                    "demon_original")
            _, flowconf = chain.flow2(pair, extra)
            _close(flowconf, nchw(now["flowconf2"]), 1e-4)
            their_flowconf = nchw(now["flowconf2"])
            extra = depth_motion_net_inputs(image2_2, their_flowconf[:, :2], their_flowconf[:, 2:], prev_motion, K,
                                            "demon_original")
            dm = chain.dm2(pair, extra)
            _close(dm.inv_depth, nchw(now["depth2"]), 1e-4)
            _close(dm.normals, nchw(now["normal2"]), 1e-4)
            _close(dm.motion, np.concatenate([now["rotation"], now["translation"]], 1), 1e-4)
        _close(chain.refine(image1, nchw(passes[3]["depth2"])), nchw(refined), 1e-4)
        assert isinstance(out.passes[3], Prediction) and out.refined.shape == (1, 1, 192, 256)


def test_bad_checkpoints_are_one_line_and_write_nothing(tmp_path, capsys):
    shapes = demon_variables()
    out = tmp_path / "out.pt"
    # a wrong shape
    wrong = write_checkpoint(tmp_path / "wrong", {"netFlow1/conv1y/kernel": np.zeros((7, 1, 6, 32), np.float32)})
    # a checkpoint that is not DeMoN's
    other = write_checkpoint(tmp_path / "other", {"netFlow1/conv1y/bias": np.zeros(32, np.float32),
                                                   "dense/kernel": np.zeros((3, 3), np.float32)})
    # truncated files
    trunc = write_checkpoint(tmp_path / "trunc", {"netFlow1/conv1y/kernel": np.zeros(shapes["netFlow1/conv1y/kernel"],
                                                                                     np.float32)})
    data = Path(f"{trunc}.data-00000-of-00001")
    data.write_bytes(data.read_bytes()[:1000])
    index_cut = write_checkpoint(tmp_path / "index_cut", {"a": np.zeros(3, np.float32)})
    index = Path(f"{index_cut}.index")
    index.write_bytes(index.read_bytes()[:-10])
    cases = [(wrong, "netFlow1/conv1y/kernel: shape mismatch: expected [9, 1, 6, 32], found [7, 1, 6, 32]"),
             (other, "not DeMoN's v1 checkpoint: 241 of its graph's 242 variables are missing "
                     "(netFlow1/conv1y/kernel,"),
             (trunc, "truncated"), (index_cut, "not a TensorFlow checkpoint index"),
             (tmp_path / "nothing", "no such file")]
    for prefix, message in cases:
        assert convert.main([str(prefix), str(out)]) == 2
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], captured.err
        assert not out.exists()


def test_demon_test_files_run_the_converted_weights_into_mlflow(released, tmp_path):
    """data=demon_test on tiny files in DeMoN's HDF5 layout under their real names: present files
    are scored with DeMoN's protocol (nyu2 without poses: depth only, Eigen's crop), missing ones
    are named, and the run lands in MLflow."""
    from demon_lab_test_files import write_demon_test_files
    from mlflow.tracking import MlflowClient

    from demon_lab.app.job import run
    from tests.jobs import compose_config

    root = tmp_path / "testdata"
    write_demon_test_files(root, ["sun3d_test.h5", "nyu2_test.h5"])
    cfg = compose_config([
        "data=demon_test", f"data.root={root}", f"model.weights={released['out']}", "model.compat=demon_original",
        "train=false", "scale=paper", "data.num_workers=0", "eval.visualize=1", "eval.point_clouds=0",
        f"tracking.uri=sqlite:///{tmp_path}/mlflow.db", f"tracking.artifact_dir={tmp_path}/artifacts",
        f"cache_dir={tmp_path}/cache", "threads=2"])
    result = run(cfg)
    assert result["status"] == "finished"
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    finished = client.get_run(result["run_id"])
    assert finished.info.status == "FINISHED"
    metrics = finished.data.metrics
    assert np.isfinite(metrics["test/sun3d_test/l1_inv"]) and np.isfinite(metrics["test/sun3d_test/rot_deg"])
    assert np.isfinite(metrics["test/nyu2_test/sc_inv"]) and "test/nyu2_test/rot_deg" not in metrics
    assert not any(k.startswith("test/rgbd_test") for k in metrics)
    assert finished.data.params["model.weights"] == str(released["out"])
    assert not (tmp_path / "cache" / "stages").exists()  # nothing trained
