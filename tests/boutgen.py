"""Still-bout pose sets for the correlated-noise tests (a wrist-like record of 10-s windows).

``n_bouts`` still bouts, each a run of consecutive 10-s windows in one orientation (a
random direction on the sphere, with a jitter of ~0.1 deg between windows), separated by
2 min to 1 h of movement. Temperature follows a daily cycle plus a slow wander, so it
changes within bouts as well as between them. The sensor is a general affine map (as in
effectgen.py) with an optional hidden ``temperature_bias`` in its forward form.

Injected noise beyond each window's measured noise (all along gravity, i.e. on the norm):

* ``sigma_bout_mg``: one error per bout, shared by its windows;
* ``sigma_ar_mg``, ``tau_s``: an AR(1) term within the bout (correlation exp(-dt/tau));
* ``sigma_white_mg``: independent per window.
"""

from __future__ import annotations

import numpy as np


def bout_case(rng, n_bouts=200, windows=(2, 40), sigma_bout_mg=0.0, sigma_ar_mg=0.0, tau_s=300.0,
              sigma_white_mg=0.0, tb_mg_per_c=0.0, sample_sd_g=6e-3, count=500, window_s=10.0):
    """One seeded case: returns (poses dict in g, truth dict). Vectorised over windows."""
    sizes = rng.integers(windows[0], windows[1] + 1, n_bouts)
    n = int(sizes.sum())
    bout = np.repeat(np.arange(n_bouts), sizes)
    first = np.r_[0, np.cumsum(sizes)[:-1]]
    pos = np.arange(n) - first[bout]
    gaps = rng.uniform(120.0, 3600.0, n_bouts)
    start = np.cumsum(np.r_[0.0, (sizes[:-1] - 1) * window_s + gaps[1:]])
    t_s = start[bout] + pos * window_s
    g = rng.normal(size=(n_bouts, 3))
    g = g[bout] + rng.normal(0.0, 1e-3, (n, 3))  # ~0.1 deg between windows of a bout
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    temp = 27.0 + 5.0 * np.sin(2 * np.pi * t_s / 86400.0) + 2.0 * np.sin(2 * np.pi * t_s / 5400.0 + rng.uniform(0, 6.3))
    # noise on the norm (g), in the true specific force
    eps = sigma_white_mg * 1e-3 * rng.standard_normal(n)
    eps += sigma_bout_mg * 1e-3 * rng.standard_normal(n_bouts)[bout]
    if sigma_ar_mg > 0:
        u = np.empty(n)
        z = rng.standard_normal(n)
        phi = np.exp(-window_s / tau_s)
        for k in range(n_bouts):  # a few hundred bouts: the test generator may loop over them
            sl = slice(first[k], first[k] + sizes[k])
            zk = z[sl]
            uk = np.empty(sizes[k])
            uk[0] = zk[0]
            for i in range(1, sizes[k]):
                uk[i] = phi * uk[i - 1] + np.sqrt(1 - phi**2) * zk[i]
            u[sl] = uk
        eps += sigma_ar_mg * 1e-3 * u
    a = g * (1.0 + eps)[:, None]
    scale = 1 + rng.uniform(-0.03, 0.03, 3)
    k = np.tril(rng.uniform(-1, 1, (3, 3)) * np.deg2rad(0.6), -1) + np.eye(3)
    offset = rng.uniform(-0.06, 0.06, 3)
    raw = a @ (np.diag(scale) @ k).T + offset
    axis = int(rng.integers(3))
    raw[:, axis] += 1e-3 * tb_mg_per_c * (temp - 25.0)
    cnt = np.full(n, float(count))
    raw += rng.normal(0, 1, raw.shape) * sample_sd_g / np.sqrt(cnt)[:, None]
    poses = {"mean": raw, "sd": np.full((n, 3), sample_sd_g), "count": cnt, "t_s": t_s, "temp_c": temp}
    truth = {"bout": bout, "sigma_bout_mg": sigma_bout_mg, "sigma_ar_mg": sigma_ar_mg, "tau_s": tau_s,
             "sigma_white_mg": sigma_white_mg, "axis": "xyz"[axis], "tb_mg_per_c": tb_mg_per_c,
             "noise_mg": sample_sd_g / np.sqrt(count) * 1e3}
    return poses, truth
