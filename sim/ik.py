"""Damped-least-squares inverse kinematics for one site, on a scratch MjData.

Each iteration takes the 6-vector error e = [p* - p; log(R* R^T)] (position, then the rotation
taking the current frame to the target, as an axis-angle vector in the world frame), the site
Jacobian J (6, n) from ``mj_jacSite`` over the arm's joints, and steps
``dq = J^T (J J^T + lambda^2 I)^-1 e``, clipped per joint, then clamps q to the joint ranges.
The damping keeps the step bounded near singularities at the cost of some accuracy there.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from services.core.geometry import rotation_error


@dataclass(frozen=True)
class IkResult:
    q: np.ndarray  # (n,) joint solution
    pos_err: float  # m, at the solution
    rot_err: float  # rad, at the solution
    iters: int


class SiteIk:
    def __init__(
        self,
        model: mujoco.MjModel,
        site: str,
        joints: tuple[str, ...],
        damping: float = 0.02,
        max_iters: int = 30,
        max_dq: float = 0.25,
        pos_tol: float = 1e-4,
        rot_tol: float = 1e-3,
    ):
        self._model = model
        self._data = mujoco.MjData(model)  # scratch: solving never touches the simulated state
        self._site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        if self._site < 0:
            raise ValueError(f"site {site!r} is not in the model")
        jids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in joints]
        self._qadr = np.array([model.jnt_qposadr[j] for j in jids])
        self._dadr = np.array([model.jnt_dofadr[j] for j in jids])
        self._lo = np.array([model.jnt_range[j][0] for j in jids])
        self._hi = np.array([model.jnt_range[j][1] for j in jids])
        self.damping, self.max_iters, self.max_dq = damping, max_iters, max_dq
        self.pos_tol, self.rot_tol = pos_tol, rot_tol
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Site (pos (3,), R (3, 3)) at joint positions q."""
        self._data.qpos[self._qadr] = q
        mujoco.mj_kinematics(self._model, self._data)
        return self._data.site_xpos[self._site].copy(), self._data.site_xmat[self._site].reshape(3, 3).copy()

    def solve(self, q_seed: np.ndarray, pos: np.ndarray, R: np.ndarray) -> IkResult:
        """Joint positions near ``q_seed`` that put the site at (pos, R)."""
        q = np.clip(np.asarray(q_seed, dtype=np.float64).copy(), self._lo, self._hi)
        lam2 = self.damping**2
        d = self._data
        for it in range(self.max_iters + 1):
            d.qpos[self._qadr] = q
            mujoco.mj_kinematics(self._model, d)
            mujoco.mj_comPos(self._model, d)
            e_p = pos - d.site_xpos[self._site]
            e_r = rotation_error(R, d.site_xmat[self._site].reshape(3, 3))
            pe, re = float(np.linalg.norm(e_p)), float(np.linalg.norm(e_r))
            if (pe < self.pos_tol and re < self.rot_tol) or it == self.max_iters:
                break
            mujoco.mj_jacSite(self._model, d, self._jacp, self._jacr, self._site)
            J = np.vstack([self._jacp[:, self._dadr], self._jacr[:, self._dadr]])  # (6, n)
            e = np.concatenate([e_p, e_r])
            dq = J.T @ np.linalg.solve(J @ J.T + lam2 * np.eye(6), e)
            dq = np.clip(dq, -self.max_dq, self.max_dq)
            q = np.clip(q + dq, self._lo, self._hi)
        return IkResult(q=q, pos_err=pe, rot_err=re, iters=it)
