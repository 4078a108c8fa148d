"""DeMoN's networks as plain nn.Modules: blocks, flow net, depth-motion net, refinement net, chain."""

from demon_lab.nets.chain import DeMoN, Prediction
from demon_lab.nets.depth_motion_net import DepthMotion, DepthMotionNet
from demon_lab.nets.flow_net import FlowNet
from demon_lab.nets.refine_net import RefineNet

__all__ = ["DeMoN", "DepthMotion", "DepthMotionNet", "FlowNet", "Prediction", "RefineNet"]
