"""Multi-view composition of a single-view diffusion policy, one denoising step at a time.

The paper's Algorithm 1 (multiview policy composition). A policy trained on pseudo-demos predicts
the noise ``eps_theta(y, k, o_v)`` of a chunk ``y`` expressed in view v's action space. With V
cameras observing the same scene, sampling from the product of the per-view distributions

    p(a | o_1..o_V)  ∝  prod_v p_v(a | o_v)^{gamma_v}

is done by combining the per-view noise predictions at every step, each brought back into one
common frame, before one scheduler update of one shared noisy chunk::

    x_K ~ N(0, I)                                    # the shared chunk, (Tp, 7), normalised
    for k in the DDIM timesteps:
        y_v   = G_v x_k                              # into view v's frame
        e_v   = eps_theta(y_v, k, o_v)               # one step of the single-view model
        eps   = sum_v gamma_v G_v^T e_v              # back into the shared frame, weighted
        x_k-1 = scheduler.step(eps, k, x_k)          # DDIM, x_0 clipped to [-1, 1]

``G_v = F_v F_ref^T`` where F_v is the view's transform in *normalised* action space: block
diagonal (R_ext of the view on dp, the same on drot, 1 on the gripper) for the camera space, the
identity for the base and EEF spaces (their actions do not depend on the camera). The shared
chunk lives in the frame of a reference view ``ref`` (the first of the views used, in the
checkpoint's camera order), exactly as the paper's update ``a^{t-1} = a^t - F^v(delta^t)`` applies
one view's F^v to the aggregated step: with one view this *is* the single-view sampler, and the
order the views arrive in changes nothing. ``x_ref = F_ref x_base`` with any other reference is
the same chunk up to where the [-1, 1] clipping of x_0 is applied.

Why this is the product of experts: for a diffusion model eps_theta(x_k, k) = -sigma_k *
grad log p_k(x_k), so a weighted sum of noise predictions is the score of the product
prod_v p_v^{gamma_v}. Each G_v is orthogonal (a rotation per 3-vector block), so G_v^T is its
inverse and it carries gradients into the shared frame unchanged in length. That holds in
normalised space only because the normaliser divides each 3-vector block by ONE scale shared by
all views, with no offset (``check_orthogonal`` refuses a normaliser that does otherwise).
The weights must sum to one: the sum is then a score of the right magnitude at every noise level;
with weights summing to V the noise estimate is V times too large, the predicted x_0 is pushed
out to the [-1, 1] clipping box, and the clipping hides how wrong the result is.

``gammas``: convex weights, 1/V by default; a view lost in mid-request is dropped and the rest
renormalised (``renormalise``). Optional, with a checkpoint trained with condition dropout: the
exact product with an unconditional branch, composable-diffusion style,
``eps = e_u + sum_v w_v (e_v - e_u)`` (``compose_with_unconditional``; with w_v = 1 the exact
posterior of views independent given the action).

Everything here is array maths on numpy or torch tensors of shape (..., Tp, 7); no transport.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from services.core.action_spaces import ACTION_DIM, check_space
from services.core.normalizer import Normalizer


class CompositionError(ValueError):
    """Views, weights or a normaliser that cannot be composed; the message says which."""


def view_transform(space: str, R_ext: np.ndarray | None = None) -> np.ndarray:
    """F_v (7, 7) in normalised action space: R_ext on dp and on drot, 1 on the gripper (camera
    space); the identity for base and EEF (the actions do not depend on the camera)."""
    F = np.eye(ACTION_DIM)
    if check_space(space) == "camera":
        if R_ext is None:
            raise CompositionError("the camera action space needs each view's R_ext (calibration)")
        R = np.asarray(R_ext, dtype=np.float64).reshape(3, 3)
        F[0:3, 0:3] = R
        F[3:6, 3:6] = R
    return F


def check_orthogonal(normalizer: Normalizer, transforms: Mapping[str, np.ndarray], atol: float = 1e-6) -> None:
    """Refuse a normaliser under which a view's transform is not orthogonal in normalised space.

    With x_n = (x - offset) / scale per component, the raw transform F acts on normalised
    actions as S^-1 F S (plus an offset term). That is F itself, orthogonal, only if each rotated
    3-vector block has one scale and no offset.
    """
    scale = np.asarray(normalizer.action_scale, dtype=np.float64)
    offset = np.asarray(normalizer.action_offset, dtype=np.float64)
    if np.any(scale <= 0) or not np.all(np.isfinite(scale)):
        raise CompositionError(f"normaliser scales must be positive and finite, got {scale.tolist()}")
    for name, F in transforms.items():
        F = np.asarray(F, dtype=np.float64)
        M = (F * scale[None, :]) / scale[:, None]  # S^-1 F S
        if not np.allclose(M.T @ M, np.eye(ACTION_DIM), atol=atol):
            raise CompositionError(
                f"view {name!r}: the action normaliser does not scale each 3-vector block by one number "
                f"(scales {np.round(scale, 6).tolist()}), so rotating normalised actions between views is "
                "not exact; this checkpoint cannot be composed across views"
            )
        moved = np.abs(F - np.eye(ACTION_DIM)).sum(axis=0) > 0
        if np.any(np.abs(offset[moved]) > atol):
            raise CompositionError(
                f"view {name!r}: the action normaliser has an offset on rotated components "
                f"({np.round(offset, 6).tolist()}); composition needs none"
            )


def default_gammas(views: Sequence[str]) -> dict[str, float]:
    """1/V for each of V views."""
    if not views:
        raise CompositionError("no views to compose")
    return {v: 1.0 / len(views) for v in views}


def checked_weights(weights: Mapping[str, float], views: Sequence[str]) -> dict[str, float]:
    """The weights of ``views`` as floats; CompositionError naming the first that is not finite and
    non-negative (the rule of every composition: the server's, a request's, eval's --gamma)."""
    w = {v: float(weights[v]) for v in views}
    for v, x in w.items():
        if not np.isfinite(x) or x < 0:
            raise CompositionError(f"the weight of {v} must be finite and non-negative, got {x}")
    return w


def renormalise(gammas: Mapping[str, float], views: Sequence[str]) -> dict[str, float]:
    """The weights of ``views`` only, scaled to sum to one (a view dropped mid-request)."""
    missing = [v for v in views if v not in gammas]
    if missing:
        raise CompositionError(f"no weight for view(s) {', '.join(missing)}")
    w = checked_weights(gammas, views)
    total = sum(w.values())
    if total <= 0:
        raise CompositionError(f"the weights of {', '.join(views)} sum to zero")
    return {v: x / total for v, x in w.items()}


def relative_transforms(
    transforms: Mapping[str, np.ndarray], order: Sequence[str]
) -> tuple[str, dict[str, np.ndarray]]:
    """(reference view, G_v = F_v F_ref^T per view): ``order`` fixes the reference (its first view)."""
    views = [v for v in order if v in transforms]
    if not views:
        raise CompositionError("no views to compose")
    ref = views[0]
    F_ref = np.asarray(transforms[ref], dtype=np.float64)
    G = {}
    for v in views:
        F = np.asarray(transforms[v], dtype=np.float64)
        # F F^T is the identity up to rounding; make it exactly so (one view is the single-view sampler)
        G[v] = np.eye(ACTION_DIM) if np.array_equal(F, F_ref) else F @ F_ref.T
    return ref, G


def _matmul(G: np.ndarray, x: Any) -> Any:
    """(..., Tp, 7) @ G^T per row, for numpy arrays or torch tensors."""
    if isinstance(x, np.ndarray):
        return x @ G.T.astype(x.dtype)
    import torch  # only when given torch tensors; the module stays importable without torch

    return x @ torch.as_tensor(G.T, dtype=x.dtype, device=x.device)


def to_view(x: Any, G: np.ndarray) -> Any:
    """y_v = G_v x: the shared chunk in view v's frame."""
    return x if np.array_equal(G, np.eye(ACTION_DIM)) else _matmul(G, x)


def from_view(e: Any, G: np.ndarray) -> Any:
    """G_v^T e: a view's noise prediction back in the shared frame (G_v^T is G_v's inverse)."""
    return e if np.array_equal(G, np.eye(ACTION_DIM)) else _matmul(G.T, e)


def weighted_sum(
    eps: Mapping[str, Any],
    G: Mapping[str, np.ndarray],
    gammas: Mapping[str, float],
    order: Sequence[str],
    total: float | None = None,
) -> Any:
    """sum_v gamma_v G_v^T e_v over the views of ``eps``, in ``order``.

    Written as ``total * d_1 + sum_v gamma_v (d_v - d_1)`` with d_v = G_v^T e_v and total =
    sum(gamma): the same value, but bit-exact d_1 when every view predicts the same (identical
    views reproduce the single-view sampler exactly). No check on the weights: see ``compose``.
    """
    views = [v for v in order if v in eps]
    if not views:
        raise CompositionError("no view predictions to compose")
    d = {v: from_view(eps[v], G[v]) for v in views}
    first = d[views[0]]
    total = sum(float(gammas[v]) for v in views) if total is None else total
    out = first * total if total != 1.0 else first
    for v in views[1:]:
        diff = d[v] - first
        out = out + diff * float(gammas[v])
    return out


def compose(
    eps: Mapping[str, Any], G: Mapping[str, np.ndarray], gammas: Mapping[str, float], order: Sequence[str]
) -> Any:
    """The composed noise of one step: convex weights over the views that answered."""
    views = [v for v in order if v in eps]
    return weighted_sum(eps, G, renormalise(gammas, views), views, total=1.0)


def compose_with_unconditional(
    eps: Mapping[str, Any],
    eps_uncond: Mapping[str, Any],
    G: Mapping[str, np.ndarray],
    weights: Mapping[str, float],
    order: Sequence[str],
) -> Any:
    """Composable diffusion: ``e_u + sum_v w_v G_v^T (e_v - e_u,v)``.

    ``eps_uncond[v]`` is the unconditional prediction (condition dropped) at view v's input G_v x,
    and the first term the one of the reference view (G_ref = I). With every w_v = 1 this is the
    exact posterior of views that are independent given the action,
    p(a | o_1..o_V) ∝ p(a) prod_v p(a | o_v) / p(a); with convex weights it reduces to ``compose``
    (the unconditional terms cancel), so the weights are taken as they are, not renormalised.
    """
    views = [v for v in order if v in eps]
    if not views:
        raise CompositionError("no view predictions to compose")
    w = checked_weights(weights, views)
    out = eps_uncond[views[0]]
    for v in views:
        out = out + from_view(eps[v] - eps_uncond[v], G[v]) * w[v]
    return out
