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
# # 2. Preprocessing: from an RGB-D pair to what the trackers read
#
# Before any tracking, every frame is turned into images the trackers and the fusion can use.
# The paper describes its part in section IV-A.1: metric depth $M$, the intensity image $I$, a
# four-level pyramid built with a 5x5 Gaussian, and the intensity derivatives by a 3x3 Sobel
# operator after a 3x3 Gaussian blur with $\sigma = 0.8$, one GPU thread per pixel. The other
# part, the **bilateral filter** and the **vertex and normal maps** that ICP reads, is
# KinectFusion's measurement stage (Newcombe et al. 2011), which Kintinuous inherits (section
# III) and the paper does not restate. This lesson takes `kintinuous_ref/preprocess.py` step by
# step:
#
# 1. the depth cut-off (metric depth, holes, far readings),
# 2. the bilateral filter: its spatial and range weights, a from-scratch loop on a small patch
#    against the package, and what it does at a depth edge,
# 3. the pyramid levels and the edge-aware downsampling of depth,
# 4. vertex maps by back-projection and normal maps by cross products, checked against the
#    known plane normals of a synthetic frame with exact geometry,
# 5. intensity from RGB and the Sobel gradients of the RGB-D tracker, checked on a ramp,
# 6. `kintinuous_fast` against the reference, within the tolerances of the tests,
# 7. a real frame (redkitchen, or a TUM sequence you have).
#
# Prerequisites: lesson 0 (poses), lesson 1 (the camera model). Its time, warm,
# is in notebooks/README.md's table.

# %%
# %matplotlib inline
import inspect

import matplotlib.pyplot as plt
import numpy as np

from kintinuous_fast.preprocess import cpu as kintinuous_fast_preprocess_cpu
from kintinuous_ref import preprocess
from kintinuous_ref.camera import axial_noise
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.course_data import load_course_data, skip_line
from kintinuous_ref.datasets.synthetic import KINECT_CAMERA

WIDTH, HEIGHT = 160, 120
config = Config()
settings = config.preprocess
camera = KINECT_CAMERA.resized(WIDTH, HEIGHT)
rng = np.random.default_rng(0)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit vectors (..., 3) (NaN where either is NaN)."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


# %% [markdown]
# ## A synthetic frame with exact geometry
#
# Three planes seen by a 160x120 Kinect-like camera: a tilted wall 1.8 m away at the image
# centre, a floor 0.6 m below the camera, and the front of a box 1.1 m away facing the camera
# (a 0.7 m depth step at its border). For the
# ray $\mathbf{d} = K^{-1}(u, v, 1)^\top$ of a pixel, a plane $\mathbf{n}\cdot\mathbf{X} = c$ is
# hit at depth $z = c / (\mathbf{n}\cdot\mathbf{d})$, so every pixel's depth and normal are known
# exactly. A window in the wall looks out 7.5 m far (beyond the sensor's range), and the measured
# depth gets the Kinect's axial noise $\sigma(z)$ (`camera.axial_noise`: about 2 mm at 1 m,
# 5 mm at 1.8 m) and the TUM format: uint16, 5000 units per metre.

# %%
rays = camera.ray_directions()  # (H, W, 3), z = 1
wall_normal = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
planes = {  # name: (unit normal facing the camera, c of n . X = c)
    "wall": (wall_normal, wall_normal @ [0.0, 0.0, 1.8]),
    "floor": (np.array([0.0, -1.0, 0.0]), -0.6),
    "box": (np.array([0.0, 0.0, -1.0]), -1.1),
}
depths = {}
for name, (normal, offset) in planes.items():
    with np.errstate(divide="ignore"):
        z = offset / (rays @ normal)
    depths[name] = np.where(z > 0, z, np.inf)
box_points = rays * depths["box"][..., None]
on_box = (np.abs(box_points[..., 0] + 0.1) < 0.18) & (np.abs(box_points[..., 1] + 0.04) < 0.18)
depths["box"] = np.where(on_box, depths["box"], np.inf)
names = list(planes)
label = np.argmin(np.stack([depths[name] for name in names]), axis=0)  # nearest surface
exact_depth = np.min(np.stack([depths[name] for name in names]), axis=0)
exact_normals = np.stack([planes[name][0] for name in names])[label]
window = (label == 0) & (np.abs(rays[..., 0] - 0.45) < 0.1) & (np.abs(rays[..., 1] + 0.2) < 0.12)
measured = exact_depth + rng.normal(size=exact_depth.shape) * axial_noise(exact_depth)
measured[window] = 7.5
raw_depth = np.round(measured * camera.depth_scale).astype(np.uint16)
print({name: int((label == k).sum()) for k, name in enumerate(names)}, "pixels;",
      f"window {window.sum()} pixels")  # fmt: skip
assert np.isfinite(exact_depth).all() and window.sum() > 100
assert abs(axial_noise(1.8) - 0.0049) < 0.0001 and abs(axial_noise(1.0) - 0.0019) < 0.0001

# %% [markdown]
# ## 1. Metric depth and the cut-off
#
# `metric_depth` divides integer sensor units by the depth scale (TUM: 5000 per metre) and sets
# 0, the code for "no measurement", wherever the reading is missing, not finite, or beyond
# `preprocess.max_depth` = 6 m. The paper converts to metres and says nothing of a range; the
# 6 m is the authors' released code's (its RGB-D odometry drops readings beyond `MAX_DEPTH` =
# 6 m), and the package applies it to every reading: a structured-light sensor's error grows
# with the square of the depth (at 6 m $\sigma$ is about 6 cm), so far readings would add more
# noise than surface.

# %%
print(inspect.getsource(preprocess.metric_depth))
depth = preprocess.metric_depth(raw_depth, settings.max_depth, camera.depth_scale)
assert depth.dtype == np.float32 and (depth[window] == 0).all() and (depth[~window] > 0).all()
np.testing.assert_allclose(depth[~window], raw_depth[~window] / 5000.0, rtol=1e-7)
print(
    f"the window's {window.sum()} pixels at 7.5 m are dropped (0); "
    f"sigma at 6 m = {1000 * axial_noise(6.0):.0f} mm"
)
assert round(100 * axial_noise(6.0)) == 6

# %% [markdown]
# ## 2. The bilateral filter
#
# Depth noise makes normals (differences of neighbouring vertices) very rough, and ICP reads
# normals. A Gaussian blur would smooth the noise but also the depth edges, inventing surface
# between a box and the wall behind it. The bilateral filter weighs each neighbour $q$ of pixel
# $p$ by its distance in the image **and** its difference in depth:
#
# $$ D'(p) = \frac{\sum_{q} w_s(\lVert p-q\rVert)\,w_r(|D(p)-D(q)|)\,D(q)}{\sum_q w_s\,w_r},
# \qquad w_s(d) = e^{-d^2/2\sigma_s^2},\quad w_r(\delta) = e^{-\delta^2/2\sigma_r^2}, $$
#
# over a $(2r+1)^2$ window. Neighbours across a depth step have $w_r \approx 0$ and do not count.
# The paper gives no values; the package's defaults, $\sigma_s$ = 4.5 pixels, $\sigma_r$ = 3 cm,
# $r$ = 6 (13x13), are those of the open-source KinectFusion (PCL's KinFu). Pixels without
# depth neither give nor receive a value. The package writes the sum as shifted copies of the image
# (one array operation per offset):

# %%
print(inspect.getsource(preprocess.bilateral_filter))
assert (settings.bilateral_sigma_space, settings.bilateral_sigma_depth) == (4.5, 0.03)
assert settings.bilateral_radius == 6

# %% [markdown]
# The same formula written as the GPU would run it, one pixel at a time with a loop over its
# window, on a 24x24 patch that straddles the box's border, checked equal to the package on the
# same patch (float32 output: to a float32 rounding).


# %%
def bilateral_from_scratch(patch: np.ndarray, sigma_s: float, sigma_r: float, r: int):  # noqa: ANN201
    """The bilateral filter pixel by pixel (0 = no depth)."""
    height, width = patch.shape
    out = np.zeros_like(patch, dtype=np.float64)
    for v in range(height):
        for u in range(width):
            centre = float(patch[v, u])
            if centre <= 0:
                continue
            total = weights = 0.0
            for dv in range(-r, r + 1):
                for du in range(-r, r + 1):
                    if 0 <= v + dv < height and 0 <= u + du < width and patch[v + dv, u + du] > 0:
                        q = float(patch[v + dv, u + du])
                        w = np.exp(-(du * du + dv * dv) / (2 * sigma_s**2))
                        w *= np.exp(-((centre - q) ** 2) / (2 * sigma_r**2))
                        total, weights = total + w * q, weights + w
            out[v, u] = total / weights
    return out


rows, cols = np.nonzero(on_box & (label == 2))
top, left = rows.min() - 12, cols.min() - 12
patch = depth[top : top + 24, left : left + 24]
assert len(np.unique(label[top : top + 24, left : left + 24])) >= 2  # the patch has an edge
scratch = bilateral_from_scratch(patch, 4.5, 0.03, 6)
package = preprocess.bilateral_filter(patch, 4.5, 0.03, 6)
print(f"24x24 patch: |from scratch - package| <= {np.abs(scratch - package).max():.1e} m")
np.testing.assert_allclose(package, scratch, rtol=2.4e-7)

# %% [markdown]
# On the whole frame: the RMS error against the exact depth on each plane (away from depth
# edges) and within 3 pixels of an edge, for the raw depth, the bilateral filter, the same
# filter applied to the *exact* depth (its bias alone), and the filter with the range weight
# switched off ($\sigma_r$ = 1 km: a plain Gaussian that ignores holes). Three things show:
#
# - on the box, which faces the camera, the filter removes nearly all the noise (more than a
#   factor of 5);
# - on the floor, seen at a grazing angle, it makes the depth **worse**: the depth of a plane is
#   not linear in the pixel coordinates ($1/z$ is), and an average of a curved profile is biased
#   (the "exact" row: millimetres of error with no noise at all). On such surfaces the bias
#   exceeds the noise the filter removes;
# - at the edges the bilateral filter stays within a factor of 2 of the raw error, while the
#   Gaussian averages the box with the wall, an error of more than 10 cm.

# %%
filtered = preprocess.bilateral_filter(depth, 4.5, 0.03, 6)
filtered_exact = preprocess.bilateral_filter(exact_depth.astype(np.float32), 4.5, 0.03, 6)
gaussian = preprocess.bilateral_filter(depth, 4.5, 1000.0, 6)
edge = np.zeros_like(on_box)
for dv in range(-3, 4):
    for du in range(-3, 4):
        edge |= np.roll(label, (dv, du), axis=(0, 1)) != label
edge[:3], edge[-3:], edge[:, :3], edge[:, -3:] = False, False, False, False
flat, band = ~edge & ~window, edge & ~window


def rms_mm(estimate: np.ndarray, where: np.ndarray) -> float:
    return 1000 * float(np.sqrt(np.mean((estimate[where] - exact_depth[where]) ** 2)))


regions = {name: flat & (label == k) for k, name in enumerate(names)} | {"edges": band}
images = {"raw": depth, "bilateral": filtered, "bilateral of exact": filtered_exact,
          "gaussian": gaussian}  # fmt: skip
table = {row: {region: rms_mm(image, where) for region, where in regions.items()}
         for row, image in images.items()}  # fmt: skip
print("RMS error (mm)      " + "".join(f"{region:>9s}" for region in regions))
for row, errors in table.items():
    print(f"{row:20s}" + "".join(f"{error:9.2f}" for error in errors.values()))
assert table["bilateral"]["box"] < table["raw"]["box"] / 5  # "more than a factor of 5"
assert table["bilateral"]["floor"] > table["raw"]["floor"]  # worse on the grazing floor
assert table["bilateral of exact"]["floor"] > 1.0  # "millimetres" of bias without noise
assert table["bilateral"]["edges"] < 2 * table["raw"]["edges"]
assert table["gaussian"]["edges"] > 100

fig, axes = plt.subplots(1, 3, figsize=(14, 3.4))
shown = np.where(depth > 0, depth, np.nan)
for ax, image, title in zip(axes, (shown, filtered, gaussian),
                            ("raw depth (m)", "bilateral", "Gaussian (no range weight)"),
                            strict=True):  # fmt: skip
    picture = ax.imshow(np.where(image > 0, image, np.nan), cmap="viridis", vmin=1.2, vmax=3.2)
    ax.set_title(title)
    ax.axis("off")
fig.colorbar(picture, ax=axes, fraction=0.02)
plt.show()
row = (rows.min() + rows.max()) // 2
fig, ax = plt.subplots(figsize=(8, 3))
ax.plot(exact_depth[row], "k-", lw=2, label="exact")
ax.plot(depth[row], ".", color="grey", ms=3, label="raw")
ax.plot(filtered[row], "-", label="bilateral")
ax.plot(gaussian[row], "--", label="Gaussian")
ax.set_xlabel("column u")
ax.set_ylabel("depth (m)")
ax.set_title(f"row {row}: across the box")
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## 3. The pyramid
#
# The trackers work coarse to fine (paper IV-A: four levels), so every image is halved three
# times: 160x120, 80x60, 40x30, 20x15. Level $l+1$'s pixel $(u, v)$ is a 5x5 Gaussian average
# (the binomial kernel $[1,4,6,4,1]/16$ in each direction, the paper's "5x5 Gaussian") centred
# on level $l$'s pixel $(2u, 2v)$, and its camera has halved focal lengths and principal point
# (`camera.at_level`). For depth, the average ignores neighbours more than 9 cm ($3\sigma_r$)
# from the centre pixel, as KinectFusion does, so a coarse pixel never averages a foreground and
# a background. Below, level 1 with and without that cut-off: pixels farther than 5 cm from the
# exact depth at their centre are "flying" between the box and the wall.

# %%
print(inspect.getsource(preprocess.pyramid_down_depth))
with_cutoff = preprocess.pyramid_down_depth(filtered, settings.pyramid_depth_cutoff)
without = preprocess.pyramid_down_depth(filtered, np.inf)
centre_truth = exact_depth[::2, ::2]
valid = (with_cutoff > 0) & ~window[::2, ::2]
pyramids = {"with the 9 cm cut-off": with_cutoff, "without": without}
flying = {name: int((np.abs(image - centre_truth)[valid] > 0.05).sum())
          for name, image in pyramids.items()}  # fmt: skip
print("level-1 pixels more than 5 cm off:", flying)
assert flying["with the 9 cm cut-off"] == 0 and flying["without"] > 20
assert settings.pyramid_depth_cutoff == 0.09

# %% [markdown]
# ## 4. Vertex and normal maps
#
# Each pixel with depth becomes a point in the camera frame, $\mathbf{V}(u,v) = D(u,v)\,K^{-1}
# (u, v, 1)^\top$ (KinectFusion; the paper's IV-A.2 computes the same $V_n(\mathbf{p})$ for the
# RGB-D tracker). Its normal is the cross product of the differences to the pixel below and to
# the pixel on the right,
#
# $$ \mathbf{n}(u,v) = \frac{(\mathbf{V}(u,v{+}1) - \mathbf{V}(u,v)) \times
# (\mathbf{V}(u{+}1,v) - \mathbf{V}(u,v))}{\lVert\cdot\rVert}, $$
#
# in this order so that it points towards the camera ($\mathbf{n}\cdot\mathbf{V} < 0$). On the
# exact depth every normal whose three pixels lie on one plane equals that plane's normal (up to
# float32 rounding); on noisy depth the bilateral filter is what makes them usable. The package
# computes vertex and normal maps from the **filtered** depth, while the TSDF (lesson 1) fuses
# the **raw** depth.

# %%
print(inspect.getsource(preprocess.normal_map))
same_plane = (label == np.roll(label, -1, axis=0)) & (label == np.roll(label, -1, axis=1))
same_plane[-1], same_plane[:, -1] = False, False
exact_vertices = preprocess.vertex_map(exact_depth.astype(np.float32), camera)
exact_map = preprocess.normal_map(exact_vertices)
exact_error = angle_deg(exact_map, exact_normals)[same_plane]
interior = same_plane & flat
raw_error = angle_deg(preprocess.normal_map(preprocess.vertex_map(depth, camera)), exact_normals)
filtered_normals = preprocess.normal_map(preprocess.vertex_map(filtered, camera))
filtered_error = angle_deg(filtered_normals, exact_normals)
medians = [float(np.nanmedian(error[interior])) for error in (raw_error, filtered_error)]
print(f"exact depth: largest normal error {exact_error.max():.3f} deg on {same_plane.sum()} pixels")
print(
    f"noisy depth, median normal error on the planes: raw {medians[0]:.1f} deg, "
    f"bilateral {medians[1]:.1f} deg"
)
assert exact_error.max() < 0.05  # float32 rounding of the vertices only
assert medians[1] < medians[0] / 3
assert np.all(np.sum(exact_map * exact_vertices, axis=-1)[same_plane] < 0)  # towards the camera

raw_normals = preprocess.normal_map(preprocess.vertex_map(depth, camera))
fig, axes = plt.subplots(1, 3, figsize=(14, 3.4))
for ax, image, title in zip(axes, (exact_map, raw_normals, filtered_normals),
                            ("normals, exact depth", "raw noisy depth", "bilateral-filtered"),
                            strict=True):  # fmt: skip
    ax.imshow(np.nan_to_num(np.abs(image)))
    ax.set_title(title + " (|n| as RGB)")
    ax.axis("off")
plt.show()

# %% [markdown]
# At every level the package back-projects with that level's camera, so the normals of level 2
# (40x30) of the preprocessed frame are still the planes' normals away from edges:

# %%
colour = np.zeros((HEIGHT, WIDTH, 3), np.uint8)  # grey stripes in the world on the wall
stripes = 128 + 80 * np.sin(2 * np.pi * (rays[..., 0] * exact_depth) / 0.2)
colour[:] = np.clip(np.where(label == 0, stripes, 60 + 80 * (label == 2)), 0, 255)[..., None]
frame = preprocess.preprocess_frame(colour, raw_depth, camera, settings)
print([f"{level.depth.shape[1]}x{level.depth.shape[0]}" for level in frame.levels])
level_2 = frame.levels[2]
assert level_2.camera == camera.at_level(2) and level_2.depth.shape == (30, 40)
coarse_labels = label[::4, ::4]
coarse_interior = interior[::4, ::4] & np.isfinite(level_2.normals).all(axis=-1)
coarse_error = angle_deg(level_2.normals, exact_normals[::4, ::4])[coarse_interior]
print(
    f"level 2: median normal error {np.median(coarse_error):.1f} deg on {coarse_interior.sum()} "
    "pixels"
)
assert np.median(coarse_error) < medians[1]

# %% [markdown]
# ## 5. Intensity and its gradients
#
# The RGB-D tracker (lesson 3) compares grey values, $I = 0.299R + 0.587G + 0.114B$ (IV-A.1), and
# its Jacobian needs $\partial I/\partial u$ and $\partial I/\partial v$: a 3x3 Gaussian blur with
# $\sigma = 0.8$ and then the 3x3 Sobel operator, as the paper says. The code scales the Sobel
# response by $1/8$ (a ramp rising by one per pixel gives the raw Sobel response 8), so that it
# reads **intensity units per pixel**; the paper does not state a scale, and the RGB-D
# tracker's minimum gradients (12 / 5 / 3 / 1, lesson 3) are in these units. Both kernels are
# symmetric and sum to one (the blur) or measure the slope (the Sobel), so on a linear ramp
# $I = a u + b v + c$ the result is exactly $(a, b)$ away from the border, a closed-form check:

# %%
print(inspect.getsource(preprocess.intensity_gradients))
u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
ramp = (0.7 * u - 1.3 * v + 200.0).astype(np.float32)
dx, dy = preprocess.intensity_gradients(ramp, settings.gradient_blur_sigma)
inner = (slice(2, -2), slice(2, -2))
np.testing.assert_allclose(dx[inner], 0.7, atol=1e-4)
np.testing.assert_allclose(dy[inner], -1.3, atol=1e-4)
print("ramp 0.7 u - 1.3 v: gradients (0.7, -1.3) per pixel away from the border")
grey = preprocess.intensity_image(np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255]]], np.uint8))
np.testing.assert_allclose(grey[0], [0.299 * 255, 0.587 * 255, 0.114 * 255], rtol=1e-6)

level_0 = frame.levels[0]
magnitude = np.hypot(level_0.intensity_dx, level_0.intensity_dy)
fig, axes = plt.subplots(1, 3, figsize=(14, 3.4))
axes[0].imshow(level_0.intensity, cmap="gray")
axes[0].set_title("intensity I")
for ax, image, title in (
    (axes[1], level_0.intensity_dx, "dI/du"),
    (axes[2], magnitude, "|grad I|"),
):
    picture = ax.imshow(image, cmap="RdBu" if title == "dI/du" else "magma")
    ax.set_title(title + " (intensity per pixel)")
    fig.colorbar(picture, ax=ax, fraction=0.035)
for ax in axes:
    ax.axis("off")
plt.show()
print(f"{(magnitude >= 12).sum()} level-0 pixels reach the RGB-D tracker's g = 12")

# %% [markdown]
# **The released code's scale differs.** The authors' code (`computeDerivativeImages`) folds the
# blur into one 3x3 kernel, columns $\pm(0.52201, 0.79451, 0.52201)$, and still multiplies its
# response by the Sobel's $1/8$. On a ramp that kernel answers $2(2 \cdot 0.52201 + 0.79451) =
# 3.68$ per unit slope instead of the Sobel's 8, so its gradients are 0.46 times the slope, and
# its thresholds $g$ = 12 / 5 / 3 / 1, compared with those gradients, keep only pixels whose slope
# is at least about 26 / 11 / 6.5 / 2.2 intensity levels per pixel. The package keeps the
# numbers 12 / 5 / 3 / 1 but applies them to the exact slope, so it keeps more pixels (its
# Jacobian, lesson 3, also reads the exact slope, where the released code's reads 0.46 of it).

# %%
from scipy import ndimage  # noqa: E402

released_kernel = np.array([[0.52201, 0.0, -0.52201], [0.79451, 0.0, -0.79451],
                            [0.52201, 0.0, -0.52201]])  # fmt: skip
released_dx = ndimage.convolve(ramp.astype(np.float64), released_kernel) / 8  # times Sobel's 1/8
released_gain = float(np.median(released_dx[inner]) / 0.7)
equivalent_g = [g / released_gain for g in config.rgbd.min_gradient]
print(
    f"released kernel on the ramp: {released_gain:.3f} x the slope; its g = 12 / 5 / 3 / 1 in "
    "slope units: " + " / ".join(f"{g:.1f}" for g in equivalent_g)
)
print(
    f"level-0 pixels of the synthetic frame: {(magnitude >= 12).sum()} reach 12 (the package), "
    f"{(magnitude >= equivalent_g[0]).sum()} reach {equivalent_g[0]:.1f} (the released code)"
)
assert abs(released_gain - 3.67706 / 8) < 1e-6 and round(released_gain, 2) == 0.46
np.testing.assert_allclose(equivalent_g, [26.1, 10.9, 6.5, 2.2], atol=0.05)
assert (magnitude >= equivalent_g[0]).sum() < (magnitude >= 12).sum()

# %% [markdown]
# ## 6. The same with `kintinuous_fast`
#
# The fast backend computes every step with numba row loops (CPU) or one CUDA thread per pixel,
# and is tested equal to the reference (`tests/test_fast_preprocess.py`): depth, masks,
# intensities and gradients bit for bit on the CPU; the bilateral filter to two float32 units in
# the last place of the depth (`rtol` 2.4e-7: its weights use a float32 exponential), hence
# vertices to `atol` 1e-6 m with that `rtol` and normals to 1e-4. The same comparison here, on
# the synthetic frame, every level:

# %%
# The cpu backend's preprocessing alone (what load_backend("cpu").preprocess holds).
fast = kintinuous_fast_preprocess_cpu


def assert_frames_equal(fast_frame, reference) -> None:  # noqa: ANN001
    """Every array of every level within the tests' tolerances (NaN in the same places)."""
    np.testing.assert_array_equal(fast_frame.depth, reference.depth)
    np.testing.assert_array_equal(fast_frame.colour_mask, reference.colour_mask)
    for a, b in zip(fast_frame.levels, reference.levels, strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6, rtol=2.4e-7)
        np.testing.assert_allclose(a.normals, b.normals, atol=1e-4, rtol=0)
        for name in ("intensity", "intensity_dx", "intensity_dy"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


assert_frames_equal(fast.preprocess_frame(colour, raw_depth, camera, settings), frame)
print("kintinuous_fast (cpu) == kintinuous_ref on every level of the synthetic frame")

# %% [markdown]
# ## 7. Real data: a real frame
#
# Frame 100 of a real sequence, downsized to 160x120 (depth by nearest neighbour, so that no
# depth is invented between surfaces). Real Kinect depth has holes (black) at shiny and dark
# surfaces and along depth edges, where the projector's pattern is shadowed; the filter leaves
# them holes. The frame comes from the course's one loader, `load_course_data()`
# (notebooks/README.md): the shared 7-Scenes redkitchen frames, or a TUM RGB-D sequence you
# have; without either the cell prints one line and skips. The numbers printed are this
# frame's; they are asserted for redkitchen, and on any sequence the cell checks that the fast
# backend equals the reference and that holes stay holes.

# %%
# $KINTINUOUS_COURSE_DATA, else the shared redkitchen, else a downloaded TUM sequence
REAL = load_course_data()
print(REAL.describe() if REAL is not None else skip_line())
if REAL is not None:
    small = REAL.camera_at(WIDTH, HEIGHT)
    real_image = REAL.frame(100, WIDTH, HEIGHT)
    real_colour, real_depth = real_image.colour, real_image.depth
    real = preprocess.preprocess_frame(real_colour, real_depth, small, settings)
    assert_frames_equal(fast.preprocess_frame(real_colour, real_depth, small, settings), real)
    real_filtered = preprocess.bilateral_filter(real.depth, 4.5, 0.03, 6)
    has_depth = real.depth > 0
    change_mm = 1000 * np.abs(real_filtered - real.depth)[has_depth]
    real_magnitude = np.hypot(real.levels[0].intensity_dx, real.levels[0].intensity_dy)
    print(
        f"holes: {100 * (1 - has_depth.mean()):.1f} % of the pixels; the filter moves depth by "
        f"{np.median(change_mm):.1f} mm (median); {(real_magnitude >= 12).sum()} pixels reach "
        "g = 12; kintinuous_fast == reference"
    )
    assert np.all(real_filtered[~has_depth] == 0)  # any sequence: holes stay holes
    if REAL.is_redkitchen:  # this frame's numbers, as printed
        assert abs(100 * (1 - has_depth.mean()) - 10.5) < 0.1
        assert abs(np.median(change_mm) - 2.0) < 0.1
        assert abs((real_magnitude >= 12).sum() - 3552) < 36
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.2))
    axes[0].imshow(real_colour)
    axes[0].set_title("colour")
    axes[1].imshow(np.where(has_depth, real.depth, np.nan), cmap="viridis")
    axes[1].set_title("raw depth (holes blank)")
    axes[2].imshow(np.nan_to_num(np.abs(real.levels[0].normals)))
    axes[2].set_title("normals (filtered depth)")
    axes[3].imshow(real_magnitude, cmap="magma", vmax=40)
    axes[3].set_title("|grad I|")
    for ax in axes:
        ax.axis("off")
    plt.show()

# %% [markdown]
# ## Summary
#
# - Depth is converted to metres with 0 for "no measurement"; readings beyond 6 m are dropped
#   (not in the paper: the released code's RGB-D cut-off, where the sensor's noise reaches about
#   6 cm).
# - The bilateral filter (KinectFusion's; $\sigma_s$ 4.5 px, $\sigma_r$ 3 cm, 13x13) averages
#   only neighbours at a similar depth: on a plane facing the camera it removes nearly all the
#   noise and it keeps depth edges, where a plain Gaussian of the same width is off by more than
#   10 cm; on a plane seen at a grazing angle its bias (depth is not linear in the pixels)
#   exceeds the noise it removes.
# - The four-level pyramid halves each image with a 5x5 Gaussian (IV-A.1); for depth it ignores
#   neighbours more than 9 cm from the centre, so no coarse pixel flies between two surfaces.
# - Vertices are $D K^{-1}(u,v,1)^\top$ and normals the cross product of the differences to the
#   neighbours below and right; from exact depth they are the planes' normals to float32
#   rounding, from noisy depth only after the filter.
# - Intensity is $0.299R + 0.587G + 0.114B$ and its gradients a Sobel after a $\sigma = 0.8$
#   blur (IV-A.1), scaled to intensity per pixel: exact on a ramp. The authors' released code
#   folds the blur into one 3x3 kernel that reads 0.46 of the slope, so its thresholds
#   12 / 5 / 3 / 1 select slopes about 2.2 times steeper than the package's same numbers do.
# - `kintinuous_fast` computes the same frame within the tests' tolerances.
#
# ## Exercises
#
# Your answers go into the cell below the list, `None` until you have them. The check cell
# after it compares each answer with a truth it computes by its own route and says which
# exercises are still open; it never prints an answer.
#
# 1. **What the gradient sees of a fine texture.** For $I(u) = \sin(\omega u)$ with
#    $\omega = \pi/2$ (a period of 4 pixels), the true derivative has amplitude $\omega$. Apply
#    `preprocess.intensity_gradients` to such an image and read the amplitude of $dI/du$ away
#    from the border: what fraction of $\omega$ is it (`your_gain`)? (The check derives it in
#    closed form from the two kernels.)
# 2. **Central differences.** Write `central_normals(vertices)` that uses
#    $(\mathbf{V}(u,v{+}1) - \mathbf{V}(u,v{-}1)) \times
#    (\mathbf{V}(u{+}1,v) - \mathbf{V}(u{-}1,v))$, normalised, NaN where a neighbour is
#    missing or on the border. The check applies it to the exact synthetic depth and requires
#    the planes' normals wherever the four neighbours lie on the pixel's plane.
# 3. **The range weight's width.** Filter the noisy synthetic depth with $\sigma_r$ = 10 cm
#    instead of 3 cm: what RMS error (mm) do you get within 3 pixels of the edges
#    (`your_edge_rms_mm`, the `band` mask)? Between the 3 cm filter's and the Gaussian's?

# %%
your_gain = None  # exercise 1: amplitude of dI/du as a fraction of omega
central_normals = None  # exercise 2: your function (H, W, 3) -> (H, W, 3)
your_edge_rms_mm = None  # exercise 3


# %%
def open_exercise(number: int, *answers: object) -> bool:
    """True (and a note) while any answer of the exercise is still None."""
    if any(answer is None for answer in answers):
        print(f"exercise {number}: not answered yet (fill in its variables in the cell above)")
        return True
    return False


def check_exercise_1(gain: float | None) -> None:
    if open_exercise(1, gain):
        return
    # Closed form: a row kernel k applied to sin(w u) scales it by sum_j k_j cos(w j) (symmetric
    # k) or turns it into cos(w u) times sum_j k_j sin(w j) (antisymmetric k). The blur's column
    # part sums to one on a function of u alone.
    omega = np.pi / 2
    g = np.exp(-np.array([1.0, 0.0, 1.0]) / (2 * 0.8**2))
    g /= g.sum()
    blur_gain = g[1] + 2 * g[0] * np.cos(omega)
    sobel_gain = 2 * np.sin(omega) / 2  # Sobel/8: row weights (1, 2, 1)/4 sum to 1, (-1, 0, 1)/2
    assert abs(gain - blur_gain * sobel_gain / omega) < 0.01, "measure the amplitude again"
    print("exercise 1 correct")


def check_exercise_2(normals_of: object) -> None:
    if open_exercise(2, normals_of):
        return
    vertices = preprocess.vertex_map(exact_depth.astype(np.float32), camera)
    result = np.asarray(normals_of(vertices))
    assert result.shape == vertices.shape
    ok = np.ones_like(label, dtype=bool)
    for shift in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ok &= np.roll(label, shift, axis=(0, 1)) == label
    ok[[0, -1]], ok[:, [0, -1]] = False, False
    assert np.all(np.isnan(result[0])) and np.all(np.isnan(result[:, -1])), "NaN on the border"
    assert angle_deg(result[ok], exact_normals[ok]).max() < 0.05, "not the planes' normals"
    print("exercise 2 correct")


def check_exercise_3(edge_rms_mm: float | None) -> None:
    if open_exercise(3, edge_rms_mm):
        return
    truth = rms_mm(preprocess.bilateral_filter(depth, 4.5, 0.10, 6), band)
    assert abs(edge_rms_mm - truth) < 0.05, "filter with sigma_r = 0.10 and use `band`"
    print("exercise 3 correct")


check_exercise_1(your_gain)
check_exercise_2(central_normals)
check_exercise_3(your_edge_rms_mm)
