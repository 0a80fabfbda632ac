"""RpNet networks (Tables 1–2) and losses (eqs. 5–6), in ``flax.linen``.

Linen, not nnx: stateless modules with plain-pytree parameters make the model a pure function
``apply(variables, x)`` that jits, vmaps and serialises, and freezing the generator in stage 2 is
passing its parameters as a constant.

* :class:`Generator` — star pattern generator SPG: FC1 400→512, ReLU, FC2 512→1024 (the pattern RP_S).
* :class:`Decoder` — star pattern decoder SPD: 1024→512, ReLU, 512→400 (denoising autoencoder, §II-D).
* :class:`Classifier` — star pattern classifier SPC: FC3 1024→512, BatchNorm, ReLU, FC4 512→K (logits;
  the softmax of eq. 4 is applied in the loss / at inference).

Every dense layer takes an optional ``dot_general``: inference may multiply bfloat16 operands with
float32 accumulation (:func:`bf16_dot_general`), by default only where the hardware has bfloat16
(:func:`native_bf16`); parameters stay float32.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

__all__ = ["Classifier", "Decoder", "Generator", "bf16_dot_general", "ce_loss", "l2_penalty", "mse_loss",
           "cpu_flags", "native_bf16", "use_bf16"]

# CPU feature flags (Linux /proc/cpuinfo names) of native bfloat16 matrix products
_BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})

BN_EPSILON = 1e-5  # the Classifier's BatchNorm ε (flax's default); the inference fold reads it


def cpu_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> frozenset[str]:
    """The CPU feature flags listed in ``cpuinfo`` (Linux); empty where the file is unreadable."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        if line.startswith("flags") and ":" in line:
            return frozenset(line.split(":", 1)[1].split())
    return frozenset()


@functools.cache
def native_bf16() -> bool:
    """Whether the default JAX backend multiplies bfloat16 natively: any GPU or TPU backend, or a CPU with
    AVX512-BF16 or AMX-BF16 (elsewhere emulated bfloat16 is slower than float32; docs/design/rpnet.md).
    """
    if jax.default_backend() != "cpu":
        return True
    return bool(cpu_flags() & _BF16_CPU_FLAGS)


def use_bf16(setting: bool | None) -> bool:
    """``Config.network_bf16`` resolved: an explicit True / False, or :func:`native_bf16` for None."""
    return native_bf16() if setting is None else bool(setting)


def bf16_dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None):
    """``lax.dot_general`` on bfloat16 operands with a float32 result (float32 accumulation).

    Operands keep 8 mantissa bits (relative rounding ≤ 2⁻⁹ per entry), so a logit moves by
    ≈ 2⁻⁹·√n·(typical |w·x|), far below the gaps that decide the top-3 candidates in practice.
    """
    del precision, preferred_element_type
    return jax.lax.dot_general(lhs.astype(jnp.bfloat16), rhs.astype(jnp.bfloat16), dimension_numbers,
                               preferred_element_type=jnp.float32)


class Generator(nn.Module):
    """SPG (Table 2): (..., 400) initial inputs → (..., 1024) patterns."""

    widths: tuple[int, int] = (512, 1024)
    dot_general: Callable | None = None

    @nn.compact
    def __call__(self, x):
        x = nn.relu(nn.Dense(self.widths[0], dot_general=self.dot_general, name="fc1")(x))
        return nn.Dense(self.widths[1], dot_general=self.dot_general, name="fc2")(x)


class Decoder(nn.Module):
    """SPD (Table 2): (..., 1024) patterns → (..., n_out) reconstructed inputs."""

    hidden: int = 512
    n_out: int = 400

    @nn.compact
    def __call__(self, z):
        z = nn.relu(nn.Dense(self.hidden, name="fc2t")(z))
        return nn.Dense(self.n_out, name="fc1t")(z)


class Classifier(nn.Module):
    """SPC (Table 1): (..., 1024) patterns → (..., K) logits. BatchNorm statistics in ``batch_stats``."""

    n_classes: int
    hidden: int = 512
    dot_general: Callable | None = None

    @nn.compact
    def __call__(self, z, train: bool = False):
        z = nn.Dense(self.hidden, dot_general=self.dot_general, name="fc3")(z)
        z = nn.BatchNorm(use_running_average=not train, momentum=0.99, epsilon=BN_EPSILON, name="bn")(z)
        return nn.Dense(self.n_classes, dot_general=self.dot_general, name="fc4")(nn.relu(z))


def mse_loss(clean, reconstructed):
    """Eq. 5: mean squared error between the clean input x and the reconstruction x_r (mean over all)."""
    return jnp.mean((clean - reconstructed) ** 2)


def ce_loss(logits, labels):
    """Eq. 6: mean of −log p_y over the batch (softmax of eq. 4 inside)."""
    return jnp.mean(optax.softmax_cross_entropy_with_integer_labels(logits, labels))


def l2_penalty(params) -> jax.Array:
    """½ Σ‖W‖² over the dense kernels (biases and BatchNorm scales are not penalised; Table 3 "L2")."""
    leaves = jax.tree_util.tree_leaves_with_path(params)
    total = jnp.float32(0.0)
    for path, leaf in leaves:
        if getattr(path[-1], "key", None) == "kernel":
            total = total + 0.5 * jnp.sum(leaf**2)
    return total
