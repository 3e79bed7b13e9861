"""The per-sample math in plain floats: eq. (4) both ways, the tool's weight, small vectors.

`WristKernel` is a `WristModel` (model.py, the numpy reference) with everything that does not
change between samples precomputed (R_st, its transpose, p_st, the calibration rows, the
stiffness), so one sample costs a few dozen float operations instead of a dozen numpy calls
on 3-vectors (each ~1 µs of overhead). It gives the same numbers as the model to rounding
(tests/control/force/test_kernel.py). Conjugation and the rotation vector commute,
log(M_t^s · exp(θ) · M_s^t) = M_t^s θ for |θ| < π, so eq. (4)'s rotation part needs no
matrix exponential or logarithm; a rotation of π or more (never a real wrist's deflection)
falls back to the model, which wraps it exactly as before.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from services.control.force.model import WristModel
from services.control.force.sensors import Six
from services.geometry import M9, V3

ZERO3: V3 = (0.0, 0.0, 0.0)
_WRAP_RAD = math.pi - 1e-3
"""Rotation vectors at least this long go through the numpy model (exact wrap at π)."""


def mat9(m: object) -> M9:
    """9 row-major floats of a 3×3 array or a sequence of 9."""
    a = np.asarray(m, dtype=float).reshape(9)
    return (
        float(a[0]),
        float(a[1]),
        float(a[2]),
        float(a[3]),
        float(a[4]),
        float(a[5]),
        float(a[6]),
        float(a[7]),
        float(a[8]),
    )


def vec3(v: object) -> V3:
    a = np.asarray(v, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def transpose(m: M9) -> M9:
    return (m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8])


def mul(m: M9, x: float, y: float, z: float) -> V3:
    """m · (x, y, z)."""
    return (
        m[0] * x + m[1] * y + m[2] * z,
        m[3] * x + m[4] * y + m[5] * z,
        m[6] * x + m[7] * y + m[8] * z,
    )


def cross(a: V3, b: V3) -> V3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def weight_wrench(mass_kg: float, gravity_mps2: float, com_t: V3, tool_R: M9) -> tuple[V3, V3]:
    """A mass's weight at the tool point, tool frame (plain-float `ToolLoad.wrench`).

    F_g = m (M_w^t)ᵀ (0, 0, −g) = −m g · (third row of M_w^t),  C_g = c × F_g.
    """
    w = -mass_kg * gravity_mps2
    f = (w * tool_R[6], w * tool_R[7], w * tool_R[8])
    return f, cross(com_t, f)


class WristKernel:
    """Eq. (4) of `model` in plain floats: signals ↔ (F_t, C_t) at the tool point, tool frame.

    Immutable like the model: build a new kernel when the model changes (set_tool,
    compliance). Methods take and return tuples of floats.
    """

    __slots__ = (
        "_Kl",
        "_Kr",
        "_Rst",
        "_Rts",
        "_cal",
        "_cal_identity",
        "_cal_inv",
        "_exact",
        "_pst",
        "_q",
        "model",
    )

    def __init__(self, model: WristModel) -> None:
        self.model = model
        self._exact = model.mode == "exact"
        self._Rst = mat9(model.R_st)
        self._Rts = transpose(self._Rst)
        self._pst = vec3(model.p_st)
        self._q = mul(self._Rts, *self._pst)  # M_t^s p_st
        self._Kl = vec3(model.K_l)
        self._Kr = vec3(model.K_r)
        self._cal_identity = bool(np.array_equal(model.calibration, np.eye(6)))
        self._cal = tuple(tuple(float(x) for x in row) for row in model.calibration)
        self._cal_inv = tuple(tuple(float(x) for x in row) for row in model.calibration_inv)

    def _rotate(self, th: V3, v: V3, sign: float) -> V3:
        """ΔM v (sign +1) or ΔM⁻¹ v (sign −1), ΔM = rot(θ) in the model's rotation mode."""
        tx, ty, tz = th
        vx, vy, vz = v
        kx, ky, kz = ty * vz - tz * vy, tz * vx - tx * vz, tx * vy - ty * vx  # θ × v
        kkx, kky, kkz = ty * kz - tz * ky, tz * kx - tx * kz, tx * ky - ty * kx  # θ × (θ × v)
        a2 = tx * tx + ty * ty + tz * tz
        if self._exact:
            # Rodrigues: exp(±θ) v = v ± (sin a / a) θ×v + ((1 − cos a) / a²) θ×(θ×v)
            if a2 < 1e-16:
                s, c = 1.0, 0.5
            else:
                a = math.sqrt(a2)
                s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
            s *= sign
        elif sign > 0.0:  # small angle: ΔM = I + [θ]×
            s, c = 1.0, 0.0
        else:  # (I + K)⁻¹ = I + (−K + K²) / (1 + |θ|²), as K³ = −|θ|² K
            s = c = 1.0 / (1.0 + a2)
            s = -s
        return (vx + s * kx + c * kkx, vy + s * ky + c * kky, vz + s * kz + c * kkz)

    def wrench_from_signals(self, sig: Sequence[float]) -> tuple[V3, V3]:
        """Six sensing signals → (F_t (N), C_t (N·m)): eq. (4), as `WristModel`'s.

        ΔT_t = M_t^s ΔM⁻¹ (ΔS − p_st) + M_t^s p_st,   C_t = K_r · M_t^s θ.
        """
        if self._cal_identity:
            dx, dy, dz, tx, ty, tz = sig
        else:
            dx, dy, dz, tx, ty, tz = (
                r[0] * sig[0]
                + r[1] * sig[1]
                + r[2] * sig[2]
                + r[3] * sig[3]
                + r[4] * sig[4]
                + r[5] * sig[5]
                for r in self._cal
            )
        if self._exact and tx * tx + ty * ty + tz * tz >= _WRAP_RAD * _WRAP_RAD:
            f, c = self.model.wrench_from_signals(np.asarray(sig, dtype=float))
            return vec3(f), vec3(c)
        p = self._pst
        w = self._rotate((tx, ty, tz), (dx - p[0], dy - p[1], dz - p[2]), -1.0)
        Rts, q, Kl, Kr = self._Rts, self._q, self._Kl, self._Kr
        t = mul(Rts, *w)
        r = mul(Rts, tx, ty, tz)
        return (
            (Kl[0] * (t[0] + q[0]), Kl[1] * (t[1] + q[1]), Kl[2] * (t[2] + q[2])),
            (Kr[0] * r[0], Kr[1] * r[1], Kr[2] * r[2]),
        )

    def signals_from_wrench(self, f: V3, c: V3) -> Six:
        """(F_t, C_t) → the six signals: eq. (4) inverted, as `WristModel`'s.

        θ = M_s^t (C_t / K_r),  ΔS = ΔM (M_s^t (F_t / K_l) − p_st) + p_st.
        """
        Rst, p, Kl, Kr = self._Rst, self._pst, self._Kl, self._Kr
        th = mul(Rst, c[0] / Kr[0], c[1] / Kr[1], c[2] / Kr[2])
        if self._exact and th[0] * th[0] + th[1] * th[1] + th[2] * th[2] >= _WRAP_RAD**2:
            s = self.model.signals_from_wrench(np.asarray(f), np.asarray(c))
            return (float(s[0]), float(s[1]), float(s[2]), float(s[3]), float(s[4]), float(s[5]))
        u = mul(Rst, f[0] / Kl[0], f[1] / Kl[1], f[2] / Kl[2])
        d = self._rotate(th, (u[0] - p[0], u[1] - p[1], u[2] - p[2]), 1.0)
        x = (d[0] + p[0], d[1] + p[1], d[2] + p[2], th[0], th[1], th[2])
        if self._cal_identity:
            return x
        return tuple(  # type: ignore[return-value]
            r[0] * x[0] + r[1] * x[1] + r[2] * x[2] + r[3] * x[3] + r[4] * x[4] + r[5] * x[5]
            for r in self._cal_inv
        )

    def wrench_from_sensor_wrench(self, fs: V3, cs: V3) -> tuple[V3, V3]:
        """A wrench at the sensor origin in R_s → at the tool point in R_t (a Net F/T).

        F_t = M_t^s F_s,   C_t = M_t^s (C_s − s_p_t × F_s)
        """
        pxf = cross(self._pst, fs)
        return (
            mul(self._Rts, *fs),
            mul(self._Rts, cs[0] - pxf[0], cs[1] - pxf[1], cs[2] - pxf[2]),
        )
