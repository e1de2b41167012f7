# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 4. Robust weights: Huber, IRLS and the trackers' weights
#
# Least squares lets every residual pull in proportion to its size, so a few wrong pairs (an
# occlusion, a specular highlight, a moving hand, a stray normal at a depth edge) can drag the
# whole estimate. Both trackers of the package weigh their residuals: the RGB-D tracker by
# $1/(\sigma' + |r|)$ (section IV-A.3 and the authors' code), ICP by Huber's kernel (the
# package's default, beyond the paper). This lesson derives where such weights come from:
#
# 1. least squares with outliers on a line fit with a known truth,
# 2. M-estimators: Huber's loss, its influence and its weight function,
# 3. iteratively reweighted least squares (IRLS) as Gauss-Newton with weights, from scratch,
#    checked against a direct minimisation of the Huber cost: IRLS recovers the line where plain
#    least squares does not,
# 4. the package's weights: `icp.robust_weights` (Huber, Tukey), `rgbd.robust_row_weights`
#    ($1/(\sigma'+|r|)$) and the default combined weighting `"huber"`, each checked against a
#    from-scratch version, and the ICP system checked to be the IRLS normal equations,
# 5. the distribution of RGB-D residuals on a real pair of frames and the weights they get.
#
# Prerequisites: lesson 0 (Gauss-Newton, normal equations), lesson 3 (RGB-D residuals) helps.
# Its time, warm, is in notebooks/README.md's table.

# %%
# %matplotlib inline
import inspect
from types import SimpleNamespace

import matplotlib.pyplot as plt
import numpy as np
import scipy.optimize

from kintinuous_ref import preprocess, se3
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.course_data import load_course_data, skip_line
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.odometry import combined, icp, rgbd

WIDTH, HEIGHT = 160, 120
config = Config()
rng = np.random.default_rng(4)

# %% [markdown]
# ## Least squares and outliers
#
# A line $y = a x + b$ with known $a = 0.8$, $b = 0.3$, 60 points with Gaussian noise of
# $\sigma = 0.05$, and 15 of them (a quarter) replaced by outliers: values drawn anywhere between
# $-2$ and $3$. Least squares minimises $\sum_k r_k^2$ with $r_k = a x_k + b - y_k$; the
# outliers' squares dominate the sum and pull the fit off the line.

# %%
true_line = np.array([0.8, 0.3])
NOISE = 0.05
x = np.sort(rng.uniform(-1.0, 1.0, 60))
y = true_line[0] * x + true_line[1] + rng.normal(0.0, NOISE, 60)
outlier = np.zeros(60, dtype=bool)
outlier[rng.choice(60, 15, replace=False)] = True
y[outlier] = rng.uniform(-2.0, 3.0, outlier.sum())
design = np.column_stack([x, np.ones_like(x)])  # the Jacobian of r with respect to (a, b)
least_squares = np.linalg.solve(design.T @ design, design.T @ y)
ls_error = np.abs(least_squares - true_line).max()
print(f"least squares: a = {least_squares[0]:.3f}, b = {least_squares[1]:.3f} "
      f"(error {ls_error:.3f}); truth a = 0.8, b = 0.3")  # fmt: skip
assert outlier.sum() == 15 and ls_error > 0.1  # the fit is visibly off

# %% [markdown]
# ## M-estimators and Huber's loss
#
# An **M-estimator** replaces the square by a loss $\rho(r)$ that grows more slowly for large
# residuals and minimises $E = \sum_k \rho(r_k)$. Huber's loss is quadratic in a core of
# half-width $k$ and linear beyond it:
#
# $$ \rho_H(r) = \begin{cases} \tfrac12 r^2 & |r| \le k \\ k|r| - \tfrac12 k^2 & |r| > k
# \end{cases}, \qquad \psi_H(r) = \rho_H'(r) = \begin{cases} r & |r|\le k \\ k\,\mathrm{sign}(r)
# & |r| > k \end{cases}. $$
#
# $\psi$ is the **influence** of a residual on the estimate: for least squares it grows without
# bound, for Huber it is capped at $k$. Tukey's biweight goes further: its influence returns to
# zero beyond $c$, so gross outliers have none. With $k = 1.345\sigma$ (Tukey: $c =
# 4.685\sigma$) either keeps 95 % of least squares' efficiency when the residuals are truly
# Gaussian with spread $\sigma$ (the classical tunings, `icp.HUBER_TUNING`, `icp.TUKEY_TUNING`).
#
# **IRLS.** Setting the gradient of $E$ to zero, $\sum_k \psi(r_k)\,\partial r_k/\partial\theta
# = 0$, and writing $\psi(r) = w(r)\,r$ with the **weight** $w(r) = \psi(r)/r$, gives
# $\sum_k w(r_k)\,r_k\,J_k = 0$: the normal equations of a *weighted* least-squares problem.
# Freeze the weights at the current residuals, take the Gauss-Newton step of the weighted
# problem,
#
# $$ (J^\top W J)\,\delta = -J^\top W \mathbf{r}, \qquad W = \mathrm{diag}(w(r_k)), $$
#
# recompute the weights, repeat: **iteratively reweighted least squares**. For Huber,
# $w(r) = 1$ in the core and $k/|r|$ beyond. Below the three losses, their influence and their
# weights, with the RGB-D tracker's weight $1/(\sigma+|r|)^2$ (next sections) and, for
# comparison, the Student-t weight $(\nu+1)/(\nu + r^2/\sigma^2)$ with $\nu = 5$ of later dense
# RGB-D odometry (Kerl, Sturm and Cremers, ICRA 2013), which this package does not use. Each
# weight is scaled to 1 at $r = 0$.


# %%
def huber_loss(r: np.ndarray, k: float) -> np.ndarray:
    magnitude = np.abs(r)
    return np.where(magnitude <= k, 0.5 * r**2, k * magnitude - 0.5 * k**2)


def tukey_loss(r: np.ndarray, c: float) -> np.ndarray:
    inside = 1 - np.minimum((r / c) ** 2, 1.0)
    return c**2 / 6 * (1 - inside**3)


residual_axis = np.linspace(-6, 6, 601)  # in units of sigma
k_huber, c_tukey = icp.HUBER_TUNING, icp.TUKEY_TUNING
weights_shown = {
    "least squares": np.ones_like(residual_axis),
    "Huber k = 1.345": icp.robust_weights(residual_axis, "huber", k_huber),
    "Tukey c = 4.685": icp.robust_weights(residual_axis, "tukey", c_tukey),
    "RGB-D 1/(1+|r|)^2": 1 / (1 + np.abs(residual_axis)) ** 2,
    "Student-t nu = 5 (not used)": 6 / (5 + residual_axis**2),
}
losses = {
    "least squares": 0.5 * residual_axis**2,
    "Huber k = 1.345": huber_loss(residual_axis, k_huber),
    "Tukey c = 4.685": tukey_loss(residual_axis, c_tukey),
}
fig, axes = plt.subplots(1, 3, figsize=(15, 3.6))
for name, loss in losses.items():
    axes[0].plot(residual_axis, loss, label=name)
    axes[1].plot(residual_axis, np.gradient(loss, residual_axis), label=name)
for name, weight in weights_shown.items():
    axes[2].plot(residual_axis, weight / weight[300], label=name)
axes[0].set_ylim(0, 8)
axes[1].set_ylim(-3, 3)
for ax, title in zip(axes, ("loss rho(r)", "influence psi(r) = rho'(r)", "weight w(r) = psi(r)/r"),
                     strict=True):  # fmt: skip
    ax.set_title(title)
    ax.set_xlabel("residual r / sigma")
axes[0].legend(fontsize=8)
axes[2].legend(fontsize=7)
plt.show()
# The weights are psi / r of the losses, by finite differences (away from r = 0).
away = np.abs(residual_axis) > 0.1
for name in ("Huber k = 1.345", "Tukey c = 4.685"):
    psi = np.gradient(losses[name], residual_axis)
    ratio = psi[away] / residual_axis[away]  # central differences blur the kink at k by 0.5 %
    np.testing.assert_allclose(ratio, weights_shown[name][away], atol=5e-3)
# Tukey's influence is zero beyond c: those residuals have no say at all; Huber's never is.
assert np.all(weights_shown["Tukey c = 4.685"][np.abs(residual_axis) >= c_tukey] == 0)
assert weights_shown["Huber k = 1.345"].min() > 0

# %% [markdown]
# The "95 %" of the tunings: for Gaussian residuals of spread 1 the variance of an M-estimate is
# $E[\psi^2] / E[\psi']^2$ times that of least squares, so its efficiency is
# $E[\psi']^2 / E[\psi^2]$, two integrals against the Gaussian density.

# %%
import scipy.integrate  # noqa: E402
import scipy.stats  # noqa: E402


def gaussian_efficiency(psi, psi_prime, limit: float) -> float:  # noqa: ANN001
    """E[psi']^2 / E[psi^2] for standard Gaussian residuals (psi zero beyond `limit`)."""
    density = scipy.stats.norm.pdf
    slope = scipy.integrate.quad(lambda r: psi_prime(r) * density(r), -limit, limit)[0]
    inside = scipy.integrate.quad(lambda r: psi(r) ** 2 * density(r), -limit, limit)[0]
    return slope**2 / (inside + 2 * psi(limit) ** 2 * scipy.stats.norm.sf(limit))


efficiency = {
    "Huber": gaussian_efficiency(
        lambda r: r if abs(r) < k_huber else np.sign(r) * k_huber, lambda r: 1.0, k_huber
    ),
    "Tukey": gaussian_efficiency(
        lambda r: r * (1 - (r / c_tukey) ** 2) ** 2 * (abs(r) < c_tukey),
        lambda r: (1 - (r / c_tukey) ** 2) * (1 - 5 * (r / c_tukey) ** 2),
        c_tukey,
    ),
}
print("efficiency at the Gaussian:", ", ".join(f"{k} {v:.4f}" for k, v in efficiency.items()))
assert all(abs(value - 0.95) < 0.001 for value in efficiency.values())

# %% [markdown]
# ## IRLS from scratch on the line
#
# The loop is Gauss-Newton (lesson 0) with one extra line, the weights. The line fit is linear,
# so without weights one step would be the least-squares answer; with them each step refits
# with the outliers down-weighted by what the previous fit made of them. Start from least
# squares, Huber with $k = 1.345\,\sigma$ (the noise $\sigma = 0.05$ is known here), 30 steps.


# %%
def irls(weight_of, start: np.ndarray, steps: int) -> list[np.ndarray]:
    """IRLS for the line: weights at the current residuals, weighted normal equations, step."""
    estimates = [start]
    for _ in range(steps):
        residuals = design @ estimates[-1] - y
        w = weight_of(residuals)
        delta = np.linalg.solve(design.T @ (w[:, None] * design), -design.T @ (w * residuals))
        estimates.append(estimates[-1] + delta)
    return estimates


def huber_weight(r: np.ndarray) -> np.ndarray:
    return np.where(np.abs(r) <= k_huber * NOISE, 1.0, k_huber * NOISE / np.abs(r))


huber_path = irls(huber_weight, least_squares, 30)
huber_fit = huber_path[-1]
direct = scipy.optimize.minimize(
    lambda line: huber_loss(design @ line - y, k_huber * NOISE).sum(),
    least_squares, method="BFGS", options={"gtol": 1e-12},
).x  # fmt: skip
huber_error = np.abs(huber_fit - true_line).max()
print(
    f"Huber IRLS: a = {huber_fit[0]:.4f}, b = {huber_fit[1]:.4f} (error {huber_error:.4f}); "
    f"direct minimisation of the Huber cost differs by {np.abs(huber_fit - direct).max():.1e}"
)
assert huber_error < 0.05 and ls_error > 3 * huber_error  # IRLS recovers the truth, LS does not
np.testing.assert_allclose(huber_fit, direct, atol=1e-5)  # IRLS minimises sum rho(r)
tukey_path = irls(lambda r: icp.robust_weights(r, "tukey", c_tukey * NOISE), huber_fit, 20)
tukey_error = np.abs(tukey_path[-1] - true_line).max()
print(f"Tukey IRLS (from Huber's fit): error {tukey_error:.4f}")
assert tukey_error < 0.05

fig, axes = plt.subplots(1, 2, figsize=(13, 4))
axes[0].plot(x[~outlier], y[~outlier], ".", color="grey", label="inliers")
axes[0].plot(x[outlier], y[outlier], "x", color="tab:red", label="outliers")
grid = np.array([-1.0, 1.0])
fits = {"truth": (true_line, "k-"), "least squares": (least_squares, "--"),
        "Huber IRLS": (huber_fit, "-"), "Tukey IRLS": (tukey_path[-1], ":")}  # fmt: skip
for name, (line, style) in fits.items():
    axes[0].plot(grid, line[0] * grid + line[1], style, label=name)
axes[0].set_title("the fits")
axes[0].legend(fontsize=8)
path_error = [np.abs(line - true_line).max() for line in huber_path]
axes[1].semilogy(path_error, "o-", label="Huber IRLS")
axes[1].axhline(ls_error, color="tab:orange", linestyle="--", label="least squares")
axes[1].set_xlabel("IRLS step")
axes[1].set_ylabel("max |(a, b) - truth|")
axes[1].set_title("error per step")
axes[1].legend()
plt.show()
final_weights = huber_weight(design @ huber_fit - y)
print(
    f"mean final weight: inliers {final_weights[~outlier].mean():.2f}, "
    f"outliers {final_weights[outlier].mean():.3f}"
)
assert final_weights[outlier].mean() < 0.2 < 0.8 < final_weights[~outlier].mean()

# %% [markdown]
# ## Where the package weighs residuals
#
# **ICP** (`odometry/icp.py`, beyond the paper, which uses KinectFusion's plain least squares):
# each pair's point-to-plane residual gets the IRLS weight of Huber's (default) or Tukey's
# kernel with a *fixed* spread, `config.icp.robust_noise` = 5 mm, so $k$ = 6.7 mm; the module
# docstring says why not a per-iteration median. The weight multiplies the pair's row in the
# normal equations, $A = \sum_k w_k J_k^\top J_k$, $\mathbf{b} = \sum_k w_k J_k^\top r_k$. The
# package's function, and a from-scratch version checked against it:

# %%
print(inspect.getsource(icp.robust_weights))
k_icp = icp.robust_threshold("huber", config.icp.robust_noise)
residuals_m = rng.normal(0, 0.01, 5000)  # metres
mine = np.minimum(1.0, k_icp / np.abs(residuals_m))
np.testing.assert_allclose(icp.robust_weights(residuals_m, "huber", k_icp), mine, rtol=1e-15)
print(
    f"icp Huber k = {1000 * k_icp:.2f} mm (1.345 x {1000 * config.icp.robust_noise:.0f} mm); "
    "min(1, k/|r|) == the package's weights"
)
assert abs(1000 * k_icp - 6.725) < 1e-9 and config.icp.robust_kernel == "huber"

# %% [markdown]
# And the ICP system is exactly the IRLS normal equations of those weights: on a synthetic desk
# pair (the current frame moved by a known small motion against the exact surface of the
# previous one, as in lesson 0), `IcpProblem(..., robust_kernel="huber")` gives
# $J^\top W J$ and $J^\top W \mathbf{r}$ of the pairs `icp.associate` finds, with $W$ from the
# from-scratch weights (depth noise weights off, as `model_noise=None`).

# %%
desk = make_scenario("desk", frames=40, width=WIDTH, height=HEIGHT, seed=0, noise=True)
previous_pose = desk.trajectory.poses[20]
pose = previous_pose @ se3.exp(np.array([0.005, -0.01, 0.0, 0.01, 0.0, 0.005]))
_, model_depth = desk.render_at(previous_pose, noise=False)
model_vertices = preprocess.vertex_map(model_depth, desk.camera)
model_normals = preprocess.normal_map(model_vertices) @ previous_pose[:3, :3].T
model_vertices = se3.transform_points(previous_pose, model_vertices)
current = preprocess.preprocess_frame(*desk.render(20), desk.camera, config.preprocess)
level = SimpleNamespace(camera=desk.camera, vertices=current.levels[0].vertices,
                        normals=current.levels[0].normals)  # fmt: skip
problem = icp.IcpProblem([level], [(model_vertices, model_normals)], previous_pose,
                         robust_kernel="huber")  # fmt: skip
system = problem.system(0, pose)
pairs = icp.associate(*icp.valid_points(level.vertices, level.normals), pose,
                      *icp.map_columns(model_vertices, model_normals), previous_pose,
                      desk.camera, 0.10, 20.0)  # fmt: skip
jacobian, residuals = icp.point_to_plane_rows(*pairs)
w = np.minimum(1.0, k_icp / np.abs(residuals))
np.testing.assert_allclose(system.A, (jacobian * w) @ jacobian.T, rtol=1e-10)
np.testing.assert_allclose(system.b, (jacobian * w) @ residuals, rtol=1e-10, atol=1e-12)
print(
    f"{len(residuals)} pairs, {100 * np.mean(w < 1):.0f} % of them beyond k; "
    "the package's A and b == J^T W J and J^T W r"
)

# %% [markdown]
# **RGB-D** (`odometry/rgbd.py`): the paper (IV-A.3) computes $\sigma' = \sqrt{\sigma / k_c}$
# from the sum $\sigma$ of the squared intensity differences of the $k_c$ correspondences, i.e.
# the RMS residual, and says $J_{rgbd}$ and $\mathbf{r}_{rgbd}$ are populated "according to the
# original algorithm ... including usage of $\sigma'$ for weighting". The formula itself is not
# in the paper: each row $(J_k, r_k)$ is scaled by $w_k = 1/(\sigma' + |r_k|)$ in OpenCV's
# implementation, which the paper's GPU code is based on, and in the authors' code; the package
# follows them, with $\sigma'$ the RMS the paper defines (the authors' code computes
# $\sqrt{k_c}$ instead, an operator-precedence slip shown in lesson 3). Scaling a row by $w_k$
# weighs it by $w_k^2$ in the normal equations, so the IRLS weight is
# $W(r) = 1/(\sigma'+|r|)^2$, and the influence $\psi(r) = r/(\sigma'+|r|)^2$ peaks at
# $|r| = \sigma'$ and then falls like $1/|r|$: it redescends, like Tukey's, but never to zero.
# Unlike ICP's fixed scale, $\sigma'$ is re-estimated from the residuals at every iteration.

# %%
print(inspect.getsource(rgbd.robust_row_weights))
intensity_residuals = rng.standard_t(3, 4000) * 6.0  # heavy-tailed, intensity units
sigma_prime = np.sqrt(np.sum(intensity_residuals**2) / len(intensity_residuals))
np.testing.assert_allclose(rgbd.robust_row_weights(intensity_residuals),
                           1 / (sigma_prime + np.abs(intensity_residuals)), rtol=1e-14)  # fmt: skip
print(f"sigma' = {sigma_prime:.2f}; 1 / (sigma' + |r|) == the package's row weights")
psi_axis = np.linspace(0, 10, 1001)
psi = psi_axis / (1 + psi_axis) ** 2
assert abs(psi_axis[np.argmax(psi)] - 1.0) < 0.01  # the influence peaks at |r| = sigma'

# %% [markdown]
# **The combined tracker** (`combined.weighting`, default `"huber"`): the ICP rows of ICP+RGB-D
# are Huber-weighted as above and, with `icp.depth_noise`, scaled by the noise at their depth;
# the RGB-D rows keep their $1/(\sigma'+|r|)$; the two systems are then added with ICP's share
# cut along directions few of its pairs observe (lesson 6). `combined.icp_robust_kernel` says
# which kernel the ICP rows of each tracker get:

# %%
print(
    f"combined.weighting = {config.combined.weighting!r}; ICP kernel for icp+rgbd: "
    f"{combined.icp_robust_kernel('icp+rgbd', config)!r}, for icp alone: "
    f"{combined.icp_robust_kernel('icp', config)!r}"
)
assert config.combined.weighting == "huber"
assert combined.icp_robust_kernel("icp+rgbd", config) == "huber"
for weighting in ("paper", "original-code"):
    other = SimpleNamespace(combined=SimpleNamespace(weighting=weighting), icp=config.icp)
    assert combined.icp_robust_kernel("icp+rgbd", other) == "none"

# %% [markdown]
# ## Real data: RGB-D residuals on a real pair
#
# Frames 100 and 105 of a real sequence at 160x120, with the current frame placed at its
# ground-truth pose: the photometric residuals $I_n(\mathbf{p}') - I_{n+1}(\mathbf{p})$ of
# Algorithm 2's correspondences at full resolution, their distribution against a Gaussian of
# the same RMS $\sigma'$, and the weights the tracker gives them. Real residuals have heavy
# tails (exposure changes, specularities, occlusion, the ground truth's own error of about a
# centimetre), which is what the weights are for. The frames come from the course's one loader,
# `load_course_data()` (notebooks/README.md): the shared 7-Scenes redkitchen frames, or a TUM
# RGB-D sequence you have; without either the cell prints one line and skips. The numbers
# printed are this pair's; the heavy tails are asserted on redkitchen, and on any sequence the
# cell checks what the weights guarantee: the residuals beyond $3\sigma'$ hold a smaller share
# of the weight than of the count.

# %%
# $KINTINUOUS_COURSE_DATA, else the shared redkitchen, else a downloaded TUM sequence
REAL = load_course_data()
print(REAL.describe() if REAL is not None else skip_line())
if REAL is not None:
    small = REAL.camera_at(WIDTH, HEIGHT)
    truth = REAL.groundtruth
    real_frames = [
        preprocess.preprocess_frame(frame.colour, frame.depth, small, config.preprocess)
        for frame in REAL.frames([100, 105], WIDTH, HEIGHT)
    ]
    real_problem = rgbd.RgbdProblem(real_frames[0].levels, real_frames[1].levels, truth.poses[100])
    previous_level = real_frames[0].levels[0]
    real_pairs = rgbd.correspond(
        real_problem.points(0), truth.poses[105], truth.poses[100], previous_level.depth,
        previous_level.intensity, small, config.rgbd.max_depth_change,
    )  # fmt: skip
    real_r = real_pairs.residuals
    real_w = rgbd.robust_row_weights(real_r)
    real_sigma = np.sqrt(np.mean(real_r**2))
    beyond = np.abs(real_r) > 3 * real_sigma
    gaussian_share = 0.0027  # P(|r| > 3 sigma) of a Gaussian
    share_of_weight = (real_w[beyond] ** 2).sum() / (real_w**2).sum()
    print(
        f"{len(real_r)} correspondences; sigma' = {real_sigma:.1f} intensity units; "
        f"{100 * beyond.mean():.1f} % beyond 3 sigma' (a Gaussian: 0.27 %), holding "
        f"{100 * share_of_weight:.2f} % of the normal equations' weight"
    )
    assert share_of_weight < beyond.mean()  # any sequence: the far residuals are down-weighted
    if REAL.is_redkitchen:
        assert beyond.mean() > gaussian_share  # heavier tails than a Gaussian
        assert abs(real_sigma - 30.5) < 0.5 and abs(100 * beyond.mean() - 1.5) < 0.1
        assert abs(100 * share_of_weight - 0.15) < 0.03
    fig, axes = plt.subplots(1, 2, figsize=(13, 3.8))
    bins = np.linspace(-6 * real_sigma, 6 * real_sigma, 81)
    axes[0].hist(real_r, bins, density=True, alpha=0.7, label="residuals")
    gauss = np.exp(-(bins**2) / (2 * real_sigma**2)) / np.sqrt(2 * np.pi * real_sigma**2)
    axes[0].plot(bins, gauss, "k--", label="Gaussian, same RMS")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("I_n(p') - I_(n+1)(p) (intensity units)")
    axes[0].set_title(f"{REAL.name} 100 -> 105 at the true pose")
    axes[0].legend(fontsize=8)
    order = np.argsort(real_r)
    axes[1].plot(real_r[order], (real_w[order] / real_w.max()) ** 2, label="RGB-D: w^2, scaled")
    huber_real = np.minimum(1.0, 1.345 * real_sigma / np.abs(real_r[order]))
    axes[1].plot(real_r[order], huber_real, "--", label="Huber, k = 1.345 sigma'")
    axes[1].set_xlabel("residual (intensity units)")
    axes[1].set_title("the weight each correspondence gets")
    axes[1].legend(fontsize=8)
    plt.show()

# %% [markdown]
# ## Summary
#
# - Least squares lets outliers pull without bound: on the line with a quarter of outliers it
#   misses the truth; an M-estimator $\sum\rho(r)$ bounds each residual's influence
#   $\psi = \rho'$.
# - IRLS is Gauss-Newton with weights $w = \psi(r)/r$ frozen at the current residuals,
#   $(J^\top W J)\delta = -J^\top W\mathbf{r}$; for Huber it converges to the minimiser of the
#   Huber cost and recovers the line.
# - ICP's rows in the package are Huber-weighted with a fixed 5 mm spread ($k$ = 6.7 mm), the
#   package's choice beyond the paper; its system is exactly $J^\top W J$, $J^\top W\mathbf{r}$.
# - The RGB-D tracker scales each row by $1/(\sigma'+|r|)$ with $\sigma'$ the RMS residual: the
#   paper names $\sigma'$, the formula is OpenCV's and the authors' code (whose $\sigma'$ is
#   $\sqrt{k_c}$ by a slip). Its influence peaks at
#   $|r| = \sigma'$ and falls off beyond.
# - Real photometric residuals have heavier tails than a Gaussian, and the weights take most of
#   their say away.
#
# ## Exercises
#
# Your answers go into the cell below the list, `None` until you have them. The check cell
# after it tests each answer by its own route (finite differences, its own IRLS runs) and says
# which exercises are still open; it never prints an answer.
#
# 1. **The RGB-D tracker's loss.** Find $\rho(r)$ (with $\rho(0) = 0$) whose IRLS weight
#    $\rho'(r)/r$ is $1/(\sigma + |r|)^2$, and write it as `rgbd_loss(r, sigma)`. (Hint:
#    differentiate $\ln(\sigma + |r|)$ and $\sigma/(\sigma+|r|)$.)
# 2. **Breakdown.** Outliers on one side only (a second surface behind the first, say) are
#    harder than the symmetric ones above. Repeat the line fit with 10, 20, 30, 40 and 50 % of
#    the points replaced by uniform values in $[1.5, 3]$ and Huber IRLS from least squares, 30
#    steps. From which fraction on is the error $\max|(a, b) - \text{truth}|$ above 0.1
#    (`your_breakdown_percent`, one of 10..50, or `0` if never)? Build the data as the check
#    does: `rng = np.random.default_rng(p)`, `ys = y_clean.copy()`,
#    `ys[rng.choice(60, 60 * p // 100, replace=False)] = rng.uniform(1.5, 3, 60 * p // 100)`
#    with `y_clean = 0.8 * x + 0.3 + np.random.default_rng(99).normal(0, 0.05, 60)`.
# 3. **A fixed scale.** ICP's Huber scale is fixed (5 mm). Rerun the Huber IRLS line fit with
#    $k$ computed from a scale ten times too large ($\sigma$ = 0.5): what error
#    $\max|(a, b) - \text{truth}|$ do you get (`your_wide_error`)? Why does it fall back
#    towards least squares?

# %%
rgbd_loss = None  # exercise 1: your function (r, sigma) -> rho(r)
your_breakdown_percent = None  # exercise 2
your_wide_error = None  # exercise 3


# %%
def open_exercise(number: int, *answers: object) -> bool:
    """True (and a note) while any answer of the exercise is still None."""
    if any(answer is None for answer in answers):
        print(f"exercise {number}: not answered yet (fill in its variables in the cell above)")
        return True
    return False


def check_exercise_1(loss: object) -> None:
    if open_exercise(1, loss):
        return
    sigma = 3.0
    r = np.concatenate([-np.geomspace(20, 0.1, 40), np.geomspace(0.1, 20, 40)])
    assert abs(float(loss(np.array([0.0]), sigma)[0])) < 1e-12, "rho(0) must be 0"
    derivative = (loss(r + 1e-6, sigma) - loss(r - 1e-6, sigma)) / 2e-6
    np.testing.assert_allclose(derivative / r, 1 / (sigma + np.abs(r)) ** 2, rtol=1e-5)
    print("exercise 1 correct")


def huber_line_error(ys: np.ndarray, scale: float) -> float:
    """max |(a, b) - truth| of Huber IRLS (k = 1.345 scale, 30 steps from least squares)."""
    line = np.linalg.lstsq(design, ys, rcond=None)[0]
    k = k_huber * scale
    for _ in range(30):
        r = design @ line - ys
        w = np.minimum(1.0, k / np.maximum(np.abs(r), 1e-300))
        line = np.linalg.lstsq(design * np.sqrt(w)[:, None], ys * np.sqrt(w), rcond=None)[0]
    return float(np.abs(line - true_line).max())


def check_exercise_2(percent: int | None) -> None:
    if open_exercise(2, percent):
        return
    y_clean = 0.8 * x + 0.3 + np.random.default_rng(99).normal(0, 0.05, 60)
    first = 0
    for p in (10, 20, 30, 40, 50):
        generator = np.random.default_rng(p)
        ys = y_clean.copy()
        ys[generator.choice(60, 60 * p // 100, replace=False)] = generator.uniform(
            1.5, 3, 60 * p // 100
        )
        if huber_line_error(ys, NOISE) > 0.1:
            first = p
            break
    assert percent == first, "run the five fractions again"
    print("exercise 2 correct")


def check_exercise_3(error: float | None) -> None:
    if open_exercise(3, error):
        return
    assert abs(error - huber_line_error(y, 10 * NOISE)) < 1e-3, "k = 1.345 x 0.5"
    print("exercise 3 correct")


check_exercise_1(rgbd_loss)
check_exercise_2(your_breakdown_percent)
check_exercise_3(your_wide_error)
