"""The trained networks folded into three dense layers for identification.

At inference the generator's output layer (no activation, Table 2), FC3 (Table 1) and BatchNorm with
its running statistics are consecutive affine maps, so

    FC4 ∘ relu ∘ BN ∘ FC3 ∘ FC2 ∘ relu ∘ FC1  =  FC4 ∘ relu ∘ F ∘ relu ∘ FC1,

    F(h) = (h W₂ W₃ + b₂ W₃ + b₃ − μ) · s + β,   s = γ / √(σ² + ε):

one 512 × 512 layer instead of 512 × 1024 and 1024 × 512 (20 % fewer multiply-adds), the same
function. The fold is computed once in float64 (folded logits differ from the layered float32 ones
by float32 rounding; tested). Training and checkpoints keep the paper's layers
(:func:`jstarid.algorithms.rpnet.train.predict_logits`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.rpnet.model import BN_EPSILON, bf16_dot_general

__all__ = ["InferenceWeights", "fold_networks", "inference_logits"]


class InferenceWeights(NamedTuple):
    """Three dense layers ``x ↦ x @ w + b`` (float32): input → hidden, hidden → hidden, hidden → K.

    Attributes:
        w1: (I, H₁), b1: (H₁,) — FC1 (I = 2⌊ρ/e⌋ inputs).
        w2: (H₁, H₂), b2: (H₂,) — FC2, FC3 and BatchNorm folded into one affine map.
        w3: (H₂, K), b3: (K,) — FC4 (logits).
    """

    w1: jax.Array
    b1: jax.Array
    w2: jax.Array
    b2: jax.Array
    w3: jax.Array
    b3: jax.Array


def fold_networks(variables: dict, bn_epsilon: float = BN_EPSILON) -> InferenceWeights:
    """The trained ``variables`` (generator + classifier) as :class:`InferenceWeights` (host, float64 fold).

    Args:
        variables: network variables as trained (``generator`` params; ``classifier`` params and
            ``batch_stats``); the decoder is not used at inference.
        bn_epsilon: BatchNorm's ε.

    Returns:
        :class:`InferenceWeights` on the default device.
    """
    gen = variables["generator"]
    clf, stats = variables["classifier"]["params"], variables["classifier"]["batch_stats"]

    def f64(a):
        return np.asarray(a, np.float64)

    w2, b2 = f64(gen["fc2"]["kernel"]), f64(gen["fc2"]["bias"])
    w3, b3 = f64(clf["fc3"]["kernel"]), f64(clf["fc3"]["bias"])
    scale = f64(clf["bn"]["scale"]) / np.sqrt(f64(stats["bn"]["var"]) + bn_epsilon)
    folded_w = np.matmul(w2, w3) * scale
    folded_b = (np.matmul(b2, w3) + b3 - f64(stats["bn"]["mean"])) * scale + f64(clf["bn"]["bias"])
    layers = (gen["fc1"]["kernel"], gen["fc1"]["bias"], folded_w, folded_b,
              clf["fc4"]["kernel"], clf["fc4"]["bias"])
    return InferenceWeights(*(jnp.asarray(np.asarray(a, np.float32)) for a in layers))


def _dense(x, w, b, bf16: bool):
    b = b.reshape((1,) * (x.ndim - 1) + b.shape)
    if bf16:  # the training networks' bfloat16 product (float32 accumulation)
        return bf16_dot_general(x, w, (((x.ndim - 1,), (0,)), ((), ()))) + b
    return jnp.matmul(x, w) + b


def inference_logits(weights: InferenceWeights, inputs, *, bf16: bool = False):
    """(..., I) initial inputs (eq. 3) → (..., K) float32 logits of the folded networks.

    Args:
        weights: :func:`fold_networks`'s result.
        inputs: (..., I) float32.
        bf16: matmuls on bfloat16 operands with float32 accumulation (``Config.network_bf16``).
    """
    h = jax.nn.relu(_dense(inputs, weights.w1, weights.b1, bf16))
    h = jax.nn.relu(_dense(h, weights.w2, weights.b2, bf16))
    return _dense(h, weights.w3, weights.b3, bf16)
