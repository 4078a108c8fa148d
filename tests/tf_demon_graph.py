"""DeMoN's released v1 graph transcribed into TensorFlow ops, for the tests that check demon_lab
against it (tests/test_convert.py).

Written from DeMoN's `python/depthmotionnet/blocks_original.py` (``flow_block_demon_original``,
``depthmotion_block_demon_original``, ``depth_refine_block_demon_original``), its helpers
(`python/depthmotionnet/helpers.py`: ``convrelu2_caffe_padding``, ``conv2d_caffe_padding``) and
`networks_original.py`, NHWC, on the variables of a checkpoint (name -> numpy array in
TensorFlow's layouts). It shares no code with demon_lab. The lmbspecialops kernels the graph calls
(``warp2d``, ``depth_to_flow``, ``flow_to_depth``) are CPU-only C++ ops that do not build against
current TensorFlow; they are transcribed here loop by loop in numpy from their sources
(`src/warp2d.cc`, `src/depthtoflow.cc`, `src/flowtodepth.cc`, `src/rotation_format.h`), in
float32 as the kernels compute for float inputs.
"""

from __future__ import annotations

import numpy as np
import tensorflow as tf

INTRINSICS = np.array([0.89115971, 1.18821287, 0.5, 0.5], dtype=np.float32)  # IterativeNet's constant


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


# ---------------------------------------------------------------------- lmbspecialops kernels, loop by loop


def warp2d(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """src/warp2d.cc, normalized=True, border_mode='value', border_value=0."""
    n, ch, h, w = image.shape
    out = np.zeros_like(image, dtype=np.float32)
    f32 = np.float32
    for b in range(n):
        for y in range(h):
            for x in range(w):
                vx, vy = f32(flow[b, 0, y, x]) * f32(w), f32(flow[b, 1, y, x]) * f32(h)
                px, py = f32(x) + vx, f32(y) + vy
                if not (np.isfinite(px) and np.isfinite(py)) or abs(px) > 2**30 or abs(py) > 2**30:
                    continue  # the int cast of these is undefined; it lands outside in practice
                x0, y0 = int(px), int(py)  # truncation toward zero, as Eigen's cast<int>
                a, bb = f32(px - f32(x0)), f32(py - f32(y0))
                x3, y3 = x0 + 1, y0 + 1
                if x0 >= 0 and x3 > 0 and x3 < w and y0 >= 0 and y3 > 0 and y3 < h:
                    wts = ((1 - a) * (1 - bb), a * (1 - bb), (1 - a) * bb, a * bb)
                    for c in range(ch):
                        vals = (image[b, c, y0, x0], image[b, c, y0, x3], image[b, c, y3, x0], image[b, c, y3, x3])
                        out[b, c, y, x] = sum(f32(v) * f32(wt) for v, wt in zip(vals, wts))
    return out


def rotation_matrix(r: np.ndarray) -> np.ndarray:
    """rotation_format.h ANGLEAXIS3: Eigen's AngleAxis, identity below 1e-6 rad."""
    r = r.astype(np.float64)
    angle = np.linalg.norm(r)
    if angle <= 1e-6:
        return np.eye(3)
    k = r / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def depth_to_flow(inv_depth: np.ndarray, rotation, translation) -> np.ndarray:
    """src/depthtoflow.cc, inverse_depth=True, normalize_flow=True (vectorised over pixels)."""
    rotation, translation = np.asarray(rotation), np.asarray(translation)
    n, _, h, w = inv_depth.shape
    out = np.empty((n, 2, h, w), np.float32)
    fx, fy, cx, cy = INTRINSICS[0] * w, INTRINSICS[1] * h, INTRINSICS[2] * w, INTRINSICS[3] * h
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    for b in range(n):
        with np.errstate(divide="ignore", invalid="ignore"):
            d = (1 / inv_depth[b, 0]).astype(np.float32)
            R = rotation_matrix(rotation[b]).astype(np.float32)
            ray = np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)]).astype(np.float32)
            p2 = np.einsum("ij,jhw->ihw", R, d * ray) + translation[b].astype(np.float32)[:, None, None]
            u = fx * (p2[0] / p2[2]) + cx
            v = fy * (p2[1] / p2[2]) + cy
            flow = np.stack([(u - xs) / w, (v - ys) / h])
        ok = (d > 0) & np.isfinite(d)
        out[b] = np.where(ok, flow, np.nan)
    return out


def flow_to_depth(flow: np.ndarray, rotation, translation, dtype=np.float64) -> np.ndarray:
    """src/flowtodepth.cc, normalized_flow=True, inverse_depth=True: linear triangulation of
    the two rays, solved by SVD (least squares) per pixel. The kernel solves in float32 with
    Eigen's JacobiSVD; ``dtype=np.float64`` gives the exact least-squares solution that both it
    and demon_lab (float64 normal equations) approximate, so a comparison of whole chains is not
    dominated by float32 rounding at ill-conditioned pixels."""
    rotation, translation = np.asarray(rotation), np.asarray(translation)
    n, _, h, w = flow.shape
    out = np.zeros((n, 1, h, w), np.float32)
    K = np.array([[INTRINSICS[0], 0, INTRINSICS[2]], [0, INTRINSICS[1], INTRINSICS[3]], [0, 0, 1]], dtype)
    for b in range(n):
        P1 = np.concatenate([K, np.zeros((3, 1), dtype)], 1)
        P2 = K @ np.concatenate([rotation_matrix(rotation[b]).astype(dtype), translation[b].astype(dtype)[:, None]], 1)
        for y in range(h):
            for x in range(w):
                x1 = np.array([(x + 0.5) / w, (y + 0.5) / h], dtype)
                x2 = x1 + flow[b, :, y, x].astype(dtype)
                rows, rhs = [], []
                for P, (u, v) in ((P1, x1), (P2, x2)):
                    rows += [v * P[2, :3] - P[1, :3], P[0, :3] - u * P[2, :3]]
                    rhs += [P[1, 3] - v * P[2, 3], u * P[2, 3] - P[0, 3]]
                A, r = np.array(rows, dtype), np.array(rhs, dtype)
                if not (np.isfinite(A).all() and np.isfinite(r).all()):
                    continue
                X = np.linalg.lstsq(A, r, rcond=None)[0]
                if np.isfinite(X).all() and X[2] > 0:
                    out[b, 0, y, x] = 1 / X[2]
    return out
