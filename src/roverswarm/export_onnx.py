"""ONNX graphs of trained actors, written node by node from their parameters (``onnx.helper``).

The actors are small networks of known structure, so each graph is the same arithmetic as
the Flax module it mirrors, with the parameters as constants; nothing is traced or guessed.
Shape legend: B a batch of swarms, N rovers, O flat observation size, M entity tokens per
rover, D entity width, H heads, d = D / H, A actions (2).

- Flat view (:func:`flat_actor`): ``obs`` [B, N, O] -> ``actions`` [B, N, A]. The off-policy
  observation normaliser comes first (standardise, clip to +-10); a shared network's one-hot
  rover index, concatenated after the observation in JAX, is the first layer's per-rover
  bias here (``x W = o W_o + W_id[i]``: the same sum, in another order); per-rover networks
  are one batched matrix product over the rover axis.
- Entity view (:func:`entity_actor`): ``own`` [B, N, 4], ``tokens`` [B, N, M, 11], ``mask``
  [B, N, M] bool -> ``actions`` [B, N, A], any N and M: the attention encoder and MLP head of
  :mod:`roverswarm.algos.entity`.
- Nearest view (:func:`nearest_actor`): the same inputs with M = 3K, flattened as
  :func:`roverswarm.env.entities.flat_tokens` does, then the flat view's MLP.

Outputs are deterministic actions: ``tanh`` of the off-policy actor, ``clip(mean, -1, 1)``
of the on-policy Gaussian's mean. Opset 17, IR version 8 (ONNX Runtime 1.13 or later).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from roverswarm.algos.entity import NEG
from roverswarm.algos.normalize import OBS_CLIP
from roverswarm.env.entities import OWN_FEATURES, TOKEN_FEATURES
from roverswarm.env.mars import ACTION_SIZE

OPSET = 17
IR_VERSION = 8
LAYER_NORM_EPSILON = 1e-6  # flax.linen.LayerNorm's default


class Graph:
    """An ONNX graph being written: its nodes, its constants and fresh value names."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.constants: list[onnx.TensorProto] = []
        self._names = 0

    def _fresh(self, hint: str) -> str:
        self._names += 1
        return f"{hint}_{self._names}"

    def const(self, value, dtype=np.float32) -> str:
        """A constant tensor (float32 unless ``dtype``); returns its name."""
        name = self._fresh("c")
        self.constants.append(numpy_helper.from_array(np.asarray(value, dtype), name))
        return name

    def op(self, op_type: str, *inputs: str, **attributes) -> str:
        """One node of ``op_type`` on ``inputs``; returns the name of its (single) output."""
        out = self._fresh(op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], **attributes))
        return out

    def model(self, inputs: list[onnx.ValueInfoProto], actions: str, shape: list, doc: str) -> onnx.ModelProto:
        """The model with ``inputs`` and output ``actions`` [shape] (float32)."""
        self.nodes.append(helper.make_node("Identity", [actions], ["actions"]))
        output = helper.make_tensor_value_info("actions", TensorProto.FLOAT, shape)
        graph = helper.make_graph(self.nodes, "roverswarm_actor", inputs, [output], self.constants, doc_string=doc)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="roverswarm")
        model.ir_version = IR_VERSION
        onnx.checker.check_model(model, full_check=True)
        return model


def float_input(name: str, shape: list) -> onnx.ValueInfoProto:
    """A float32 graph input (``shape`` entries: ints, or names of free dimensions)."""
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)


# ----------------------------------------------------------------------------- layers


def dense(g: Graph, x: str, p: dict) -> str:
    """``x @ kernel + bias`` (flax ``Dense``)."""
    return g.op("Add", g.op("MatMul", x, g.const(p["kernel"])), g.const(p["bias"]))


def layer_norm(g: Graph, x: str, p: dict) -> str:
    """flax ``LayerNorm`` over the last axis: mean and E[x^2] - mean^2 (clipped at 0), then
    ``(x - mean) * (rsqrt(var + eps) * scale) + bias``."""
    mean = g.op("ReduceMean", x, axes=[-1], keepdims=1)
    square_mean = g.op("ReduceMean", g.op("Mul", x, x), axes=[-1], keepdims=1)
    var = g.op("Max", g.op("Sub", square_mean, g.op("Mul", mean, mean)), g.const(0.0))
    inv = g.op("Reciprocal", g.op("Sqrt", g.op("Add", var, g.const(LAYER_NORM_EPSILON))))
    return g.op("Add", g.op("Mul", g.op("Sub", x, mean), g.op("Mul", inv, g.const(p["scale"]))), g.const(p["bias"]))


ACTIVATIONS = {"relu": "Relu", "tanh": "Tanh"}


def mlp(g: Graph, x: str, p: dict, activation: str = "relu") -> str:
    """The Dense layers ``Dense_0`` .. ``Dense_L`` of ``p``, each but the last followed by
    ``LayerNorm_i`` if ``p`` has it and ``activation`` (roverswarm's MLPs)."""
    layers = sum(1 for name in p if name.startswith("Dense_"))
    for i in range(layers):
        x = dense(g, x, p[f"Dense_{i}"])
        if i < layers - 1:
            if f"LayerNorm_{i}" in p:
                x = layer_norm(g, x, p[f"LayerNorm_{i}"])
            x = g.op(ACTIVATIONS[activation], x)
    return x


def _heads(g: Graph, x: str, heads: int, per_head: int, perm: list[int]) -> str:
    """[B, N, K, D] -> its heads [B, N, K, H, d], axes permuted by ``perm``."""
    return g.op("Transpose", g.op("Reshape", x, g.const([0, 0, 0, heads, per_head], np.int64)), perm=perm)


def attention(g: Graph, queries: str, keys: str, key_mask: str, p: dict, heads: int, project: bool) -> str:
    """roverswarm's ``MaskedAttention``: queries [B, N, Q, D] over keys [B, N, M, D] with
    ``key_mask`` [B, N, 1, 1, M] bool -> [B, N, Q, D]."""
    dim = np.shape(p["query"]["kernel"])[-1]
    per_head = dim // heads
    q = _heads(g, dense(g, queries, p["query"]), heads, per_head, [0, 1, 3, 2, 4])  # [B, N, H, Q, d]
    k = _heads(g, dense(g, keys, p["key"]), heads, per_head, [0, 1, 3, 4, 2])  # [B, N, H, d, M]
    v = _heads(g, dense(g, keys, p["value"]), heads, per_head, [0, 1, 3, 2, 4])  # [B, N, H, M, d]
    logits = g.op("Mul", g.op("MatMul", q, k), g.const(per_head**-0.5))  # [B, N, H, Q, M]
    weights = g.op("Softmax", g.op("Where", key_mask, logits, g.const(NEG)), axis=-1)
    weights = g.op("Mul", weights, g.op("Cast", key_mask, to=TensorProto.FLOAT))
    out = g.op("Transpose", g.op("MatMul", weights, v), perm=[0, 1, 3, 2, 4])  # [B, N, Q, H, d]
    out = g.op("Reshape", out, g.const([0, 0, 0, dim], np.int64))
    return dense(g, out, p["out"]) if project else out


def _norm(g: Graph, x: str, p: dict, name: str) -> str:
    return layer_norm(g, x, p[name]) if name in p else x


def entity_encoder(g: Graph, own: str, tokens: str, mask: str, p: dict, heads: int) -> str:
    """roverswarm's ``EntityEncoder`` (parameters ``p``, ``heads`` attention heads): own
    [B, N, 4], tokens [B, N, M, 11], mask [B, N, M] bool -> [B, N, 2D]."""
    tokens = g.op("Where", g.op("Unsqueeze", mask, g.const([-1], np.int64)), tokens, g.const(0.0))
    key_mask = g.op("Unsqueeze", mask, g.const([2, 3], np.int64))  # [B, N, 1, 1, M]
    u = g.op("Relu", dense(g, own, p["embed_own"]))  # [B, N, D]
    h = g.op("Relu", dense(g, tokens, p["embed_token"]))  # [B, N, M, D]
    layers = sum(1 for name in p if name.startswith("attention_"))
    for layer in range(layers):
        z = _norm(g, h, p, f"norm_attention_{layer}")
        h = g.op("Add", h, attention(g, z, z, key_mask, p[f"attention_{layer}"], heads, project=True))
        z = _norm(g, h, p, f"norm_mlp_{layer}")
        z = g.op("Relu", dense(g, z, p[f"mlp_hidden_{layer}"]))
        h = g.op("Add", h, dense(g, z, p[f"mlp_out_{layer}"]))
    z = _norm(g, h, p, "norm_pool")
    query = g.op("Unsqueeze", u, g.const([2], np.int64))  # [B, N, 1, D]
    pooled = attention(g, query, z, key_mask, p["pool"], heads, project=False)
    return g.op("Concat", u, g.op("Squeeze", pooled, g.const([2], np.int64)), axis=-1)


# ----------------------------------------------------------------------------- actors


def _deterministic(g: Graph, pre: str, squash: str) -> str:
    """``tanh`` (off-policy actors) or ``clip`` to [-1, 1] (the on-policy Gaussian's mean)."""
    if squash == "tanh":
        return g.op("Tanh", pre)
    return g.op("Clip", pre, g.const(-1.0), g.const(1.0))


def _fold_rover_ids(p: dict, obs_size: int) -> dict:
    """A shared MLP whose input is [observation, one-hot rover index]: the first layer's
    kernel rows of the index become a per-rover bias [N, H] (broadcast over [B, N, H])."""
    first = p["Dense_0"]
    kernel, bias = np.asarray(first["kernel"]), np.asarray(first["bias"])
    return {**p, "Dense_0": {"kernel": kernel[:obs_size], "bias": bias + kernel[obs_size:]}}


def _stack_rovers(p: Any) -> Any:
    """Per-rover parameters [N, ...]: every vector [N, X] as [N, 1, X], to broadcast over
    inputs [N, B, X] (kernels [N, X, Y] multiply them as a batch)."""
    if isinstance(p, dict):
        return {k: _stack_rovers(v) for k, v in p.items()}
    p = np.asarray(p)
    return p[:, None] if p.ndim == 2 else p


def flat_actor(
    mlp_params: dict,
    num_rovers: int,
    obs_size: int,
    per_rover: bool,
    activation: str,
    squash: str,
    obs_norm: tuple[np.ndarray, np.ndarray] | None,
    doc: str,
) -> onnx.ModelProto:
    """The actor of the flat view: ``obs`` [B, N, O] -> ``actions`` [B, N, A]. ``mlp_params``:
    an MLP's ``Dense_i`` (and ``LayerNorm_i``), one per rover (stacked [N, ...]) if
    ``per_rover``, else one shared MLP that reads the one-hot rover index after the
    observation; ``obs_norm``: the (mean [O], std [O]) that standardise observations first."""
    g = Graph()
    x = "obs"
    if obs_norm is not None:
        mean, std = obs_norm
        standard = g.op("Div", g.op("Sub", x, g.const(mean)), g.const(std))
        x = g.op("Clip", standard, g.const(-OBS_CLIP), g.const(OBS_CLIP))
    if per_rover:
        x = g.op("Transpose", x, perm=[1, 0, 2])  # [N, B, O]: one product per rover
        pre = g.op("Transpose", mlp(g, x, _stack_rovers(mlp_params), activation), perm=[1, 0, 2])
    else:
        pre = mlp(g, x, _fold_rover_ids(mlp_params, obs_size), activation)
    inputs = [float_input("obs", ["batch", num_rovers, obs_size])]
    return g.model(inputs, _deterministic(g, pre, squash), ["batch", num_rovers, ACTION_SIZE], doc)


def _entity_inputs(tokens: int | str) -> list[onnx.ValueInfoProto]:
    return [
        float_input("own", ["batch", "rovers", OWN_FEATURES]),
        float_input("tokens", ["batch", "rovers", tokens, TOKEN_FEATURES]),
        helper.make_tensor_value_info("mask", TensorProto.BOOL, ["batch", "rovers", tokens]),
    ]


def entity_actor(params: dict, heads: int, doc: str) -> onnx.ModelProto:
    """The on-policy entity actor (``EntityActor`` parameters ``params``: ``encoder``, ``head``):
    ``own``, ``tokens``, ``mask`` -> ``actions`` [B, N, A] (the mean, clipped), any N and M."""
    g = Graph()
    pre = mlp(g, entity_encoder(g, "own", "tokens", "mask", params["encoder"], heads), params["head"])
    return g.model(_entity_inputs("tokens"), _deterministic(g, pre, "clip"), ["batch", "rovers", ACTION_SIZE], doc)


def nearest_actor(mlp_params: dict, k: int, activation: str, squash: str, doc: str) -> onnx.ModelProto:
    """The nearest actor: ``own``, ``tokens`` [B, N, 3k, 11], ``mask`` -> ``actions``; its MLP
    reads [own, tokens (zero where masked) flattened, mask]; ``squash``: ``clip`` (the
    on-policy Gaussian's mean) or ``tanh`` (the off-policy shared actor)."""
    g = Graph()
    tokens = g.op("Where", g.op("Unsqueeze", "mask", g.const([-1], np.int64)), "tokens", g.const(0.0))
    flat = g.op("Reshape", tokens, g.const([0, 0, 3 * k * TOKEN_FEATURES], np.int64))
    x = g.op("Concat", "own", flat, g.op("Cast", "mask", to=TensorProto.FLOAT), axis=-1)
    pre = mlp(g, x, mlp_params, activation)
    return g.model(_entity_inputs(3 * k), _deterministic(g, pre, squash), ["batch", "rovers", ACTION_SIZE], doc)
