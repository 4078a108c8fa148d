"""DeMoN's released v1 graph transcribed into TensorFlow ops, for the tests that check demon_lab
against it (tests/test_convert.py).

Written from DeMoN's `python/depthmotionnet/blocks_original.py` (``flow_block_demon_original``,
``depthmotion_block_demon_original``, ``depth_refine_block_demon_original``), its helpers
(`python/depthmotionnet/helpers.py`: ``convrelu2_caffe_padding``, ``conv2d_caffe_padding``) and
`networks_original.py`, NHWC, on the variables of a checkpoint (name -> numpy array in
TensorFlow's layouts). It shares no code with demon_lab. The lmbspecialops kernels the graph calls
(``warp2d``, ``depth_to_flow``, ``flow_to_depth``) are C++ ops that do not build against current
TensorFlow; tests/lmbspecialops_reference.py transcribes them loop by loop in numpy.
"""

from __future__ import annotations

import numpy as np
import tensorflow as tf
from lmbspecialops_reference import depth_to_flow, flow_to_depth, warp2d


def leaky(x):
    """myLeakyRelu: lmbspecialops' leaky_relu, x if x > 0 else 0.1 x."""
    return tf.where(x > 0, x, 0.1 * x)


class Graph:
    def __init__(self, variables: dict[str, np.ndarray]):
        self.v = {k: tf.constant(a) for k, a in variables.items()}

    # ------------------------------------------------------------------ layers (helpers.py)
    def conv(self, x, name, kernel, stride, act=True):
        """conv2d_caffe_padding (+ myLeakyRelu): tf.pad by k//2 each side, a VALID conv."""
        kh, kw = kernel
        x = tf.pad(x, [[0, 0], [kh // 2, kh // 2], [kw // 2, kw // 2], [0, 0]])
        y = tf.nn.conv2d(x, self.v[name + "/kernel"], strides=[1, stride[0], stride[1], 1], padding="VALID")
        y = tf.nn.bias_add(y, self.v[name + "/bias"])
        return leaky(y) if act else y

    def convrelu2(self, x, name, k, stride):
        return self.conv(self.conv(x, name + "y", (k, 1), (stride, 1)), name + "x", (1, k), (1, stride))

    def refine(self, x, scope, direct, prediction=None):
        """_refine_caffe_padding: VALID transposed conv (2n + 2), leaky ReLU, slice from 1."""
        w = self.v[scope + "/upconv/kernel"]
        n, h, wd, _ = x.shape
        y = tf.nn.conv2d_transpose(x, w, [n, 2 * h + 2, 2 * wd + 2, w.shape[2]], strides=[1, 2, 2, 1],
                                   padding="VALID")
        y = leaky(tf.nn.bias_add(y, self.v[scope + "/upconv/bias"]))
        y = y[:, 1:1 + direct.shape[1], 1:1 + direct.shape[2], :direct.shape[3]]
        return tf.concat([t for t in (y, direct, prediction) if t is not None], axis=3)

    def upsample_prediction(self, x, scope):
        """_upsample_prediction: a 'same' transposed conv, no activation."""
        w = self.v[scope + "/upconv/kernel"]
        n, h, wd, _ = x.shape
        y = tf.nn.conv2d_transpose(x, w, [n, 2 * h, 2 * wd, w.shape[2]], strides=[1, 2, 2, 1], padding="SAME")
        return tf.nn.bias_add(y, self.v[scope + "/upconv/bias"])

    def predict(self, x, scope):
        """_predict_flow_caffe_padding / _predict_depthnormal_caffe_padding: conv + leaky, conv."""
        return self.conv(self.conv(x, scope + "/conv1", (3, 3), (1, 1)), scope + "/conv2", (3, 3), (1, 1), act=False)

    def dense(self, x, name, act=True):
        y = tf.matmul(x, self.v[name + "/kernel"]) + self.v[name + "/bias"]
        return leaky(y) if act else y

    # ------------------------------------------------------------------ blocks (blocks_original.py)
    def flow_block(self, net, image_pair, image2_2=None, prev=None):
        c = lambda x, name, n, k, s: self.convrelu2(x, f"{net}/{name}", k, s)  # noqa: E731
        conv1 = c(image_pair, "conv1", 32, 9, 2)
        if prev is None:
            conv2 = c(conv1, "conv2", 64, 7, 2)
            conv2_1 = c(conv2, "conv2_1", 64, 3, 1)
        else:
            conv2 = c(conv1, "conv2", 32, 7, 2)
            flow = depth_to_flow(nchw(prev["depth2"]), prev["rotation"], prev["translation"])
            norm = np.linalg.norm(flow, axis=1, keepdims=True)
            flow = np.where(np.concatenate([norm, norm], 1) < 1.0, flow, np.zeros_like(flow))
            warped = warp2d(nchw(image2_2), flow)
            extra = tf.concat([nhwc(warped), nhwc(flow), prev["depth2"], prev["normal2"]], axis=3)
            conv_extra = c(extra, "conv2_extra_inputs", 32, 3, 1)
            conv2_1 = c(tf.concat([conv2, conv_extra], axis=3), "conv2_1", 64, 3, 1)
        conv3_1 = c(c(conv2_1, "conv3", 128, 5, 2), "conv3_1", 128, 3, 1)
        conv4_1 = c(c(conv3_1, "conv4", 256, 5, 2), "conv4_1", 256, 3, 1)
        conv5_1 = c(c(conv4_1, "conv5", 512, 5, 2), "conv5_1", 512, 3, 1)
        flowconf5 = self.predict(conv5_1, f"{net}/predict_flow5")
        flowconf5to4 = self.upsample_prediction(flowconf5, f"{net}/upsample_flow5to4")
        concat4 = self.refine(conv5_1, f"{net}/refine4", conv4_1, flowconf5to4)
        concat3 = self.refine(concat4, f"{net}/refine3", conv3_1)
        concat2 = self.refine(concat3, f"{net}/refine2", conv2_1)
        return {"flowconf5": flowconf5, "flowconf2": self.predict(concat2, f"{net}/predict_flow2")}

    def depthmotion_block(self, net, image_pair, image2_2, flow2, flowconf2, rotation=None, translation=None):
        c = lambda x, name, n, k, s: self.convrelu2(x, f"{net}/{name}", k, s)  # noqa: E731
        conv1 = c(image_pair, "conv1", 32, 9, 2)
        conv2 = c(conv1, "conv2", 32, 7, 2)
        flow_nchw = nchw(flow2)
        extra = [nhwc(warp2d(nchw(image2_2), flow_nchw)), flowconf2]
        if rotation is not None:
            extra.append(nhwc(flow_to_depth(flow_nchw, rotation, translation)))
        conv_extra = c(tf.concat(extra, axis=3), "conv2_extra_inputs", 32, 3, 1)
        conv2_1 = c(tf.concat([conv2, conv_extra], axis=3), "conv2_1", 64, 3, 1)
        conv3_1 = c(c(conv2_1, "conv3", 128, 5, 2), "conv3_1", 128, 3, 1)
        conv4_1 = c(c(conv3_1, "conv4", 256, 5, 2), "conv4_1", 256, 3, 1)
        conv5_1 = c(c(conv4_1, "conv5", 512, 3, 2), "conv5_1", 512, 3, 1)
        motion_conv1 = self.conv(conv5_1, f"{net}/motion_conv1", (3, 3), (1, 1))
        flat = tf.reshape(tf.transpose(motion_conv1, [0, 3, 1, 2]), [motion_conv1.shape[0], -1])  # NCHW flatten
        fc2 = self.dense(self.dense(flat, f"{net}/motion_fc1"), f"{net}/motion_fc2")
        motion_scale = self.dense(fc2, f"{net}/motion_fc3", act=False)
        rotation, translation, scale = motion_scale[:, :3], motion_scale[:, 3:6], motion_scale[:, 6:]
        concat4 = self.refine(conv5_1, f"{net}/refine4", conv4_1)
        concat3 = self.refine(concat4, f"{net}/refine3", conv3_1)
        concat2 = self.refine(concat3, f"{net}/refine2", conv2_1)
        out = self.predict(concat2, f"{net}/predict_depthnormal2")
        depth = tf.reshape(scale, [-1, 1, 1, 1]) * out[..., :1]
        return {"depth2": depth, "normal2": out[..., 1:], "rotation": rotation, "translation": translation}

    def refine_block(self, image1, depth2):
        size = image1.shape[1:3]
        depth = tf.compat.v1.image.resize_nearest_neighbor(depth2, size)
        x = tf.concat([image1, depth], axis=3)
        conv = lambda x, name, s: self.conv(x, f"netRefine/{name}", (3, 3), (s, s))  # noqa: E731
        conv0 = conv(x, "conv0", 1)
        conv1_1 = conv(conv(conv0, "conv1", 2), "conv1_1", 1)
        conv2_1 = conv(conv(conv1_1, "conv2", 2), "conv2_1", 1)
        concat1 = self.refine(conv2_1, "netRefine/refine1", conv1_1)
        concat0 = self.refine(concat1, "netRefine/refine0", conv0)
        return self.predict(concat0, "netRefine/predict_depth0")

    # ------------------------------------------------------------------ networks_original.py / example.py
    def run(self, image_pair, image2_2, iterations=3):
        """The chain as DeMoN's examples/example.py runs it. NHWC numpy in, a list of per-pass
        dicts (flowconf2, flowconf5, depth2, normal2, rotation, translation) and the refined depth out."""
        image_pair, image2_2 = tf.constant(image_pair), tf.constant(image2_2)
        flow = self.flow_block("netFlow1", image_pair)
        dm = self.depthmotion_block("netDM1", image_pair, image2_2, flow["flowconf2"][..., :2], flow["flowconf2"])
        passes = [{**flow, **dm}]
        for _ in range(iterations):
            prev = passes[-1]
            flow = self.flow_block("netFlow2", image_pair, image2_2, prev)
            dm = self.depthmotion_block("netDM2", image_pair, image2_2, flow["flowconf2"][..., :2], flow["flowconf2"],
                                        prev["rotation"], prev["translation"])
            passes.append({**flow, **dm})
        refined = self.refine_block(image_pair[..., :3], passes[-1]["depth2"])
        as_np = lambda d: {k: np.asarray(v) for k, v in d.items()}  # noqa: E731
        return [as_np(p) for p in passes], np.asarray(refined)


def nchw(x):
    return np.transpose(np.asarray(x), (0, 3, 1, 2)).astype(np.float32)


def nhwc(x):
    return tf.constant(np.transpose(np.asarray(x, dtype=np.float32), (0, 2, 3, 1)))
