#!/usr/bin/env python3
"""F/F_Hertz of a rigid paraboloid pressed into an incompressible elastic layer bonded to a rigid
base, frictionless contact, at chi = sqrt(R delta)/h = 0.3, 0.5 and 1.

Independent of the Rust solvers: a spectral boundary-element solution on a periodic box.

* Layer compliance (Carbone & Mangialardi, J. Mech. Phys. Solids 56, 2008, eq. A.30): the
  surface displacement of a layer of thickness h bonded to a rigid base under a normal traction
  is u(q) = p(q)/K(q) with
      K(q) = (E* q/2) [(3-4nu) cosh 2qh + 2q^2h^2 + 5-12nu+8nu^2] / [(3-4nu) sinh 2qh - 2qh],
  here at nu = 0.5 exactly: K(0) is infinite, so the mean surface displacement vanishes (the
  pushed-in volume equals the bulge), the q = 0 mode of u is zero, and far from the contact the
  surface returns to its rest level; the periodic box then only adds images that decay
  exponentially with the box size over h.
* Pressures are uniform per pixel and u is sampled at pixel centres through the spectral kernel
  on the box's Brillouin zone (for a half-space this gives Love's centre displacement of a
  uniformly loaded square exactly, and Boussinesq's far field).
* Displacement control: find p >= 0 with gap r^2/(2R) - delta + u >= 0, zero where p > 0, by the
  conjugate gradient of Polonsky & Keer (Wear 231, 1999).
* F_Hertz = (4/3) E* R^(1/2) delta^(3/2). Units: h = 1, R = 1, E* = 1 (F/F_Hertz depends on
  chi only).

For each chi: the force on boxes 12h and 16h at cell a/16 (a = chi h), and the refinement from
a/16 to a/32 measured on an 8h box (where it is cheap; it hardly depends on the box). The value
printed is the 16h box's plus that refinement; box_change and grid_change are the two steps'
changes, which shrink fast with further steps (the periodic images decay exponentially with the
box over h; the force converges about as the square of the cell). Output lines:
`chi=<chi> F/F_Hertz=<value> box_change=<...> grid_change=<...>`. Needs numpy only.
"""

import sys

import numpy as np


def compliance(q, h, e_star):
    """1/K(q) of the bonded incompressible layer (nu = 0.5), 0 at q = 0."""
    s = 2.0 * q * h
    out = np.zeros_like(q)
    big = s > 40.0  # the layer is a half-space to within e^-40
    out[big] = 2.0 / (e_star * q[big])
    mid = (s > 0.0) & ~big
    sm = s[mid]
    # nu = 0.5: 3 - 4nu = 1 and 5 - 12nu + 8nu^2 = 1.
    ratio = (np.sinh(sm) - sm) / (np.cosh(sm) + 0.5 * sm * sm + 1.0)
    out[mid] = 2.0 / (e_star * q[mid]) * ratio
    return out


def solve(chi, box, cells_per_radius, h=1.0, radius=1.0, e_star=1.0, tol=1e-10):
    """F/F_Hertz on a periodic box `box` h wide with cell a/cells_per_radius, a = chi h."""
    delta = (chi * h) ** 2 / radius
    dx = chi * h / cells_per_radius
    n = int(np.ceil(box * h / dx / 2.0)) * 2
    x = (np.arange(n) - n / 2 + 0.5) * dx
    xx, yy = np.meshgrid(x, x, indexing="ij")
    gap0 = (xx**2 + yy**2) / (2.0 * radius) - delta
    qx = 2.0 * np.pi * np.fft.fftfreq(n, d=dx)
    qy = 2.0 * np.pi * np.fft.rfftfreq(n, d=dx)
    q = np.sqrt(qx[:, None] ** 2 + qy[None, :] ** 2)
    kernel = compliance(q, h, e_star)

    def displacement(p):
        return np.fft.irfft2(np.fft.rfft2(p) * kernel, s=p.shape)

    # Polonsky & Keer's conjugate gradient under displacement control.
    p = np.where(gap0 < 0.0, -gap0, 0.0) * e_star / (chi * h)
    t = np.zeros_like(p)
    g_old = 1.0
    restart = True
    for _ in range(20000):
        g = displacement(p) + gap0
        active = p > 0.0
        g_sum = np.sum(g[active] ** 2)
        beta = 0.0 if restart else g_sum / g_old
        t = np.where(active, g + beta * t, 0.0)
        g_old = g_sum
        r = displacement(t)
        denom = np.sum(r[active] * t[active])
        tau = np.sum(g[active] * t[active]) / denom if denom > 0.0 else 0.0
        p_new = np.maximum(p - tau * t, 0.0)
        overlap = (p_new == 0.0) & (g < 0.0)
        restart = bool(np.any(overlap))
        p_new[overlap] -= tau * g[overlap]
        change = np.sum(np.abs(p_new - p)) / np.sum(p_new)
        p = p_new
        if change < tol:
            break
    else:
        raise RuntimeError(f"no convergence at chi={chi}, box={box}, n={n}")
    force = p.sum() * dx * dx
    hertz = 4.0 / 3.0 * e_star * np.sqrt(radius) * delta**1.5
    return force / hertz


def main():
    for chi in (0.3, 0.5, 1.0):
        grid_change = solve(chi, 8.0, 32) - solve(chi, 8.0, 16)
        small_box = solve(chi, 12.0, 16)
        large_box = solve(chi, 16.0, 16)
        print(
            f"chi={chi} F/F_Hertz={large_box + grid_change:.4f} "
            f"box_change={large_box - small_box:+.1e} grid_change={grid_change:+.1e}"
        )
        sys.stdout.flush()


if __name__ == "__main__":
    main()
