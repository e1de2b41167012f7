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
# # 14. Loop closure and map deformation
#
# Beyond the paper, whose conclusion lists "closing large loops via SLAM pose-graph
# optimisation" as ongoing work: its authors' follow-up (Whelan, Kaess, Leonard, McDonald,
# IROS 2013; the journal Kintinuous, IJRR 2015) stops drift from piling up when the camera
# comes back to a place it has seen. Three pieces, each small (`kintinuous_ref/loop_closure/`,
# `docs/loop_closure.md`). The three steps are the follow-up's; how each is done here (ORB
# features matched directly rather than through a bag of words, the checks below, dynamic
# covariance scaling in the pose graph) is the package's own, described in docs/loop_closure.md:
#
# 1. **place recognition**: is this keyframe a place seen before, and where was the camera then?
# 2. a **pose graph** that spreads the error the loop reveals over the keyframes;
# 3. an **embedded deformation graph** (Sumner et al. 2007) that bends the map the same way.
#
# This lesson runs each on a problem with a known answer.

# %%
# %matplotlib inline
import matplotlib.pyplot as plt
import numpy as np
from scipy.sparse import identity
from scipy.sparse.linalg import spsolve

from kintinuous_ref import se3
from kintinuous_ref.config import Config, LoopClosureConfig
from kintinuous_ref.datasets.course_data import load_course_data, skip_line
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.loop_closure import deformation_graph, keyframes, place_recognition, pose_graph
from kintinuous_ref.preprocess import preprocess_frame

settings = LoopClosureConfig()

# %% [markdown]
# ## 1. Place recognition
#
# A keyframe keeps ORB features with their 3D points from the depth. A candidate old keyframe is
# accepted only after four checks: enough ratio-test matches; a rigid motion that most matched
# 3D points agree on (RANSAC over triples, Horn's closed form); the tracker's own ICP+RGB-D from
# that motion, with a small residual and most points paired; and the paired pixels' intensities
# agreeing. (A fifth, last gate refuses a loop that would move the keyframe further from where
# odometry put it than the path between the two makes plausible; exercise 1 meets it.) The
# `revisit` scenario's lap comes back to its start after 240 frames; the `twins` scenario has
# two identical bays 5 m apart.


# %%
def keyframe_of(scenario, frame, node, pose=None):
    colour, depth = scenario.render(frame)
    preprocessed = preprocess_frame(colour, depth, scenario.camera, Config().preprocess)
    pose = scenario.trajectory.poses[frame] if pose is None else pose
    return keyframes.make_keyframe(node, frame, pose, 0.0, preprocessed, settings), colour


revisit = make_scenario("revisit", frames=300, width=320, height=240)
twins = make_scenario("twins", frames=480, width=320, height=240)
# The revisit seen from a pose that odometry got 19 cm and 3 degrees wrong.
drift = se3.exp(np.array([0.0, 0.0, np.radians(3.0), 0.15, -0.1, 0.05]))
assert round(100 * np.linalg.norm(drift[:3, 3])) == 19
assert round(np.degrees(se3.rotation_angle(drift[:3, :3]))) == 3
bays_apart = np.linalg.norm(twins.trajectory.poses[390][:3, 3] - twins.trajectory.poses[90][:3, 3])
print(f"the twins' views of their bays are {bays_apart:.2f} m apart")
assert abs(bays_apart - 5.0) < 0.05
start, start_rgb = keyframe_of(revisit, 0, 0)
back, back_rgb = keyframe_of(revisit, 240, 24, drift @ revisit.trajectory.poses[240])
bay1, bay1_rgb = keyframe_of(twins, 90, 0)
bay2, bay2_rgb = keyframe_of(twins, 390, 20)
rng = np.random.default_rng(0)
true_loop = place_recognition.verify(back, start, settings, rng)
false_loop = place_recognition.verify(bay2, bay1, settings, rng)
for name, verdict in (("revisit", true_loop), ("twins", false_loop)):
    print(name, {k: v for k, v in verdict.as_dict().items() if v is not None})

figure, axes = plt.subplots(1, 4, figsize=(14, 3))
for ax, image, title in zip(
    axes,
    (start_rgb, back_rgb, bay1_rgb, bay2_rgb),
    ("revisit: frame 0", "revisit: frame 240", "twins: bay 1", "twins: bay 2"),
    strict=True,
):
    ax.imshow(image)
    ax.set_title(title)
    ax.axis("off")
plt.show()

truth = se3.inverse(start.pose) @ revisit.trajectory.poses[240]
error = np.linalg.norm(true_loop.relative[:3, 3] - truth[:3, 3])
print(f"revisit: accepted, relative pose {1000 * error:.2f} mm from the truth")
assert true_loop.accepted and error < 0.005
# The bays agree in appearance and in geometry; the texture around them does not.
assert place_recognition.naive_verify(bay2, bay1, settings, rng)
assert not false_loop.accepted and false_loop.reason == "photometric"

# %% [markdown]
# ## 2. The pose graph
#
# Keyframe poses T_i joined by odometry edges (the tracked relative pose) and loop edges. The
# error of an edge is log(Z_ij^-1 T_i^-1 T_j), divided by its standard deviation; Levenberg-
# Marquardt on the sparse normal equations minimises their squares. Loop edges are weighted by
# **dynamic covariance scaling** (Agarwal et al., ICRA 2013): a loop whose squared residual
# chi^2 contradicts the rest of the graph is weighted down by s = min(1, 2 phi / (phi + chi^2)),
# recomputed at every step, so one false loop cannot fold the map. This is the closed form of
# Suenderhauf and Protzel's switchable constraints (IROS 2012), where s would be one more unknown
# per loop with the prior (1 - s)^2 phi; here it is no unknown of the solver.
#
# Below: 30 keyframes around a circle, with odometry that drifts, one true loop closing the
# circle and one false loop claiming that opposite sides are the same place.


# %%
def circle(count, radius=2.0):
    poses = []
    for i in range(count):
        angle = 2 * np.pi * i / count
        pose = se3.exp(np.array([0.0, 0.0, angle, 0.0, 0.0, 0.0]))
        pose[:3, 3] = [radius * np.cos(angle), radius * np.sin(angle), 0.0]
        poses.append(pose)
    return np.array(poses)


truth = circle(30)
rng = np.random.default_rng(2)
odometry = [truth[0]]
for i in range(1, len(truth)):
    step = pose_graph.relative_pose(truth[i - 1], truth[i])
    odometry.append(odometry[-1] @ step @ se3.exp(rng.normal(0, 0.004, 6)))
graph = pose_graph.PoseGraph()
for pose in odometry:
    graph.add_node(pose)
for i in range(1, len(truth)):
    measured = pose_graph.relative_pose(odometry[i - 1], odometry[i])
    graph.add_edge(i - 1, i, measured, 0.01, 0.01)
graph.add_edge(0, 29, pose_graph.relative_pose(truth[0], truth[29]), 0.01, 0.01, loop=True)
graph.add_edge(5, 20, np.eye(4), 0.01, 0.01, loop=True)  # false: 4 m apart
assert len(truth) == 30 and abs(np.linalg.norm(truth[5][:3, 3] - truth[20][:3, 3]) - 4.0) < 1e-9
solution = pose_graph.optimise(graph)
print("scales s (true loop, false loop):", np.round(solution.switches, 3))

before = np.array(odometry)[:, :3, 3]
after = solution.poses[:, :3, 3]
plt.figure(figsize=(5, 5))
plt.plot(*truth[:, :2, 3].T, color="0.6", linewidth=3, label="truth")
plt.plot(*before[:, :2].T, "r.-", label="odometry")
plt.plot(*after[:, :2].T, "b.-", label="optimised")
plt.gca().set_aspect("equal")
plt.legend()
plt.show()
drifted = np.linalg.norm(before - truth[:, :3, 3], axis=1).max()
optimised = np.linalg.norm(after - truth[:, :3, 3], axis=1).max()
print(
    f"largest position error: odometry {1000 * drifted:.0f} mm, optimised {1000 * optimised:.0f} mm"
)
assert solution.switches[0] > 0.9 and solution.switches[1] < 0.1
assert optimised < 0.5 * drifted

# %% [markdown]
# ### What one loop can tell
#
# A loop measures where the camera ended up relative to where it started: the *sum* of the
# odometry errors between its ends, six numbers however many edges lie between them. Where the
# error happened must come from the edges' own uncertainty. With the same sigma on every edge
# the graph spreads a loop's error evenly; an edge given a covariance (`add_edge(...,
# covariance=C)`, 6 x 6, rotation first) takes a share in proportion to its variance along
# the error.
#
# Below, the tracker slid 5 cm along its x axis on one edge only (edge 15: a bare wall, say)
# and was exact elsewhere. Three graphs: every edge alike; edge 15 declared weak along x
# (sigma 30 cm there, as a tracker that observed nothing along x would say); and, for contrast,
# the wrong edge (5) declared weak, which helps little: its largest error is still more than
# three quarters of the one with every edge alike.

# %%
slide = np.eye(4)
slide[0, 3] = 0.05  # the 5 cm slide of edge 15
tracked = [truth[0]]
for i in range(1, len(truth)):
    step = pose_graph.relative_pose(truth[i - 1], truth[i])
    tracked.append(tracked[-1] @ step @ (slide if i == 15 else np.eye(4)))
tracked = np.array(tracked)


def position_errors(weak_edge):
    graph = pose_graph.PoseGraph()
    for pose in tracked:
        graph.add_node(pose)
    for i in range(1, len(truth)):
        sigmas = [0.01] * 3 + ([0.3, 0.01, 0.01] if i == weak_edge else [0.01] * 3)
        measured = pose_graph.relative_pose(tracked[i - 1], tracked[i])
        graph.add_edge(i - 1, i, measured, 0.01, 0.01, covariance=np.diag(np.square(sigmas)))
    graph.add_edge(0, 29, pose_graph.relative_pose(truth[0], truth[29]), 0.01, 0.01, loop=True)
    placed = pose_graph.optimise(graph).poses
    return np.linalg.norm(placed[:, :3, 3] - truth[:, :3, 3], axis=1)


spread = {label: position_errors(edge) for label, edge in
          (("every edge alike", None), ("edge 15 weak", 15), ("edge 5 weak", 5))}  # fmt: skip
plt.figure(figsize=(7, 3))
for label, errors in spread.items():
    plt.plot(1000 * errors, ".-", label=label)
plt.xlabel("keyframe")
plt.ylabel("position error (mm)")
plt.legend()
plt.show()
for label, errors in spread.items():
    print(f"{label:17s} largest error {1000 * errors.max():5.1f} mm")
assert spread["every edge alike"].max() > 0.025  # the slide, spread along the lap
assert spread["edge 15 weak"].max() < 0.005  # put back where it happened
assert spread["edge 5 weak"].max() > 0.75 * spread["every edge alike"].max()  # helps little

# %% [markdown]
# On the `revisit` scenario the tracker's errors are spread along the lap in every direction,
# and even a perfect covariance for every edge (each edge's true error direction, an oracle)
# brings the ATE only a small part of the way to what every keyframe at its true pose gives:
# docs/loop_closure.md's oracle table measures it with `benchmarks/pose_graph_oracle.py` on a
# full run, too long for a lesson. One loop at the end of a lap cannot say where along it the
# camera drifted.

# %% [markdown]
# ## 3. Embedded deformation
#
# The map that already left the moving volume was fused with the drifted poses. Nodes g_j
# sampled from it carry an affine map (R_j, t_j); a point moves to
# sum_j w_j [R_j (v - g_j) + g_j + t_j] over its nearest nodes. The maps minimise
# 1 E_rot (R_j a rotation) + 10 E_reg (neighbours agree) + 100 E_con (pinned points reach their
# targets); in a run the pinned points sit in front of each keyframe's camera and move from
# its old pose to the pose graph's.
#
# Here a flat 2 x 1 m sheet was mapped bent (up to 15 cm at one end, as drift bends a room);
# pinning both ends and the middle to their true places straightens all of it: every point ends
# within 2 cm of flat, on average within 5 mm.

# %%
u, v = np.meshgrid(np.linspace(-1, 1, 40), np.linspace(-0.5, 0.5, 20))
flat = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
mapped = flat + np.column_stack(
    [0 * u.ravel(), 0 * u.ravel(), 0.15 * np.clip(u.ravel(), 0, None) ** 2]
)
assert np.ptp(flat[:, 0]) == 2.0 and np.ptp(flat[:, 1]) == 1.0  # the 2 x 1 m sheet
assert abs(mapped[:, 2].max() - 0.15) < 1e-12  # bent up to 15 cm
times = np.zeros(len(flat))
nodes = deformation_graph.build_graph(mapped, times, spacing=0.25)
pinned = np.flatnonzero((np.abs(flat[:, 0]) > 0.9) | (np.abs(flat[:, 0]) < 0.05))
solved = deformation_graph.optimise(nodes, mapped[pinned], times[pinned], flat[pinned])
index, weights = deformation_graph.node_weights(solved, mapped, times)
straightened = deformation_graph.deform_points(solved, mapped, index, weights)

plt.figure(figsize=(8, 3))
plt.plot(mapped[::20, 0], 1000 * mapped[::20, 2], "r.", label="as mapped")
plt.plot(straightened[::20, 0], 1000 * straightened[::20, 2], "b.", label="deformed")
plt.plot(nodes.positions[:, 0], 1000 * nodes.positions[:, 2], "k+", label="nodes")
plt.xlabel("x (m)")
plt.ylabel("height (mm)")
plt.legend()
plt.show()
residual = np.linalg.norm(straightened - flat, axis=1)
print(
    f"{nodes.size} nodes; distance to the flat sheet: mean {1000 * residual.mean():.1f} mm, "
    f"largest {1000 * residual.max():.1f} mm (before: up to 150 mm)"
)
assert residual.mean() < 0.005 and residual.max() < 0.02

# %% [markdown]
# ### Why the steps are damped
#
# E_rot is the only term that is not linear in the unknowns. Linearised at R_j = I it constrains
# only the symmetric part of each step dR_j: a node whose neighbours lie on a line (a pole, a
# wall seen edge-on) can take skew steps that E_reg does not see, and the true E_rot punishes
# them quadratically. Below, a 2 m pole pinned through lever arms 0.5 m off it, its far end
# turned 20 degrees about the pole and moved 20 cm across it. Plain Gauss-Newton on the
# package's energy (`deformation_graph.energy`; every step taken) lowers the cost from 7.0 to
# 0.11 in one step and throws it above 10^12 in the next. The package's solver keeps a step only
# where it lowers the cost, damping it (J^T J + lambda I) until it does (Levenberg-Marquardt),
# and ends at 0.022. On a whole map the same divergence throws parts of it metres off
# (docs/loop_closure.md measures it on the `revisit` run).

# %%
pole = np.column_stack([np.linspace(0.0, 2.0, 81), np.zeros(81), np.zeros(81)])
pole_graph = deformation_graph.build_graph(pole, np.zeros(len(pole)), spacing=0.25)
turn = se3.exp(np.array([np.radians(20.0), 0.0, 0.0, 0.0, 0.2, 0.0]))  # [omega, u]: about x
near = np.array([[0.0, 0.5, 0.0], [0.0, 0.0, 0.5]])  # lever arms 0.5 m off the pole
far = near + [2.0, 0.0, 0.0]
sources = np.vstack([near, far])
targets = np.vstack([near, se3.transform_points(turn, far)])
terms = deformation_graph.energy(pole_graph, sources, np.zeros(4), targets)
x, plain = terms.start, [terms.cost(terms.start)]
for _ in range(10):  # plain Gauss-Newton: J^T J dx = -J^T r, every step taken
    j, r = terms.jacobian(x), terms.residuals(x)
    x = x + spsolve((j.T @ j + 1e-9 * identity(len(x))).tocsc(), -(j.T @ r))
    plain.append(terms.cost(x))
solve = deformation_graph.levenberg_marquardt
damped = [terms.cost(solve(terms.residuals, terms.jacobian, terms.start, n)) for n in range(11)]
plt.figure(figsize=(6, 3))
plt.semilogy(plain, "r.-", label="Gauss-Newton, every step taken")
plt.semilogy(damped, "b.-", label="damped steps (the package's)")
plt.xlabel("steps")
plt.ylabel("energy E")
plt.legend()
plt.show()
print(f"Gauss-Newton: {plain[0]:.1f} -> {plain[1]:.2f} -> {plain[2]:.2g}; damped: {damped[-1]:.3f}")
assert round(plain[0], 1) == 7.0 and round(plain[1], 2) == 0.11 and plain[2] > 1e12
assert round(damped[-1], 3) == 0.022 and all(np.diff(damped) <= 0)

# %% [markdown]
# ## Real data: which views are the same place
#
# The same checks on real frames from the course's loader (`load_course_data()`,
# notebooks/README.md: the shared 7-Scenes *redkitchen* frames, or a TUM sequence of yours):
# frame 0 as the old keyframe, and frames 15, 30, 60 and 150 (0.5 to 5 s later) as queries, at
# 160x120. Where a loop is accepted, its relative pose is compared with the ground truth
# (redkitchen's is KinectFusion's, good to about a centimetre); where it is rejected, the check
# that said no. The numbers asserted are redkitchen's; on another sequence the cell checks that
# no accepted loop is further from the truth than the calibration's 10 cm.

# %%
REAL = load_course_data()
print(REAL.describe() if REAL is not None else skip_line())
if REAL is not None:
    kitchen_camera = REAL.camera_at(160, 120)
    kitchen_truth = REAL.groundtruth.poses
    kitchen_keyframes, kitchen_images = {}, {}
    for node, index in enumerate((0, 15, 30, 60, 150)):
        image = REAL.frame(index, 160, 120)
        rgb, depth = image.colour, image.depth
        preprocessed = preprocess_frame(rgb, depth, kitchen_camera, Config().preprocess)
        kitchen_keyframes[index] = keyframes.make_keyframe(
            node, index, kitchen_truth[index], 0.0, preprocessed, settings
        )
        kitchen_images[index] = rgb
    verdicts, kitchen_errors_mm = {}, {}
    for index in (15, 30, 60, 150):
        verdict = place_recognition.verify(
            kitchen_keyframes[index], kitchen_keyframes[0], settings, np.random.default_rng(0)
        )
        verdicts[index] = verdict
        true_relative = se3.inverse(kitchen_truth[0]) @ kitchen_truth[index]
        apart_mm = 1000 * np.linalg.norm(true_relative[:3, 3])
        if verdict.accepted:
            kitchen_errors_mm[index] = 1000 * np.linalg.norm(
                verdict.relative[:3, 3] - true_relative[:3, 3]
            )
            outcome = f"accepted, {kitchen_errors_mm[index]:.1f} mm from the ground truth"
        else:
            outcome = f"rejected by the {verdict.as_dict()['reason']} check"
        print(f"frame {index:3d} ({apart_mm:4.0f} mm from frame 0): {outcome}")
    figure, axes = plt.subplots(1, 5, figsize=(15, 2.6))
    for ax, (index, image) in zip(axes, kitchen_images.items(), strict=True):
        ax.imshow(image)
        if index == 0:
            ax.set_title("frame 0 (old keyframe)")
        else:
            ax.set_title(f"frame {index}: " + ("loop" if verdicts[index].accepted else "no loop"))
        ax.axis("off")
    plt.show()
    assert all(error < 100 for error in kitchen_errors_mm.values())  # any sequence: no false loop
if REAL is not None and REAL.is_redkitchen:
    assert verdicts[15].accepted and verdicts[30].accepted  # the same view, moved a few cm
    assert kitchen_errors_mm[15] < 10 and kitchen_errors_mm[30] < 10  # the truth's centimetre
    # 29 cm and 6 degrees away: accepted since the calibration below, a couple of centimetres
    # from the ground truth (which is good to about a centimetre over a few frames, less over
    # two seconds)
    assert verdicts[60].accepted and kitchen_errors_mm[60] < 30
    # 82 cm and 22 degrees away, a third of the view shared: too few RANSAC inliers
    assert not verdicts[150].accepted and verdicts[150].reason == "geometry"
    from kintinuous_ref.loop_closure.calibration import true_overlap, views_apart

    for index, (metres, degrees) in ((60, (0.29, 6)), (150, (0.82, 22))):
        apart = views_apart(kitchen_truth[0], kitchen_truth[index])
        assert round(apart[0], 2) == metres and round(apart[1]) == degrees, apart
    assert round(3 * true_overlap(kitchen_keyframes[150], kitchen_keyframes[0])) == 1

# %% [markdown]
# ## Calibrating the checks on real revisits
#
# The thresholds were first set on synthetic frames, where a true revisit agrees almost
# everywhere. Real revisits come back from another distance and angle, with another exposure
# and a partial overlap: the old dense check (half of the new view's points paired) refused
# returns 15 cm and 15 degrees off. So each check's statistic is measured on candidates whose
# truth is known (`kintinuous_ref/loop_closure/calibration.py`; `benchmarks/loop_calibration.py`
# runs the full set, `docs/loop_closure.md` gives its numbers): keyframes of the real frames at
# their ground-truth poses, the candidates of a run played there and back (stride 6 here),
# offset returns (a frame against an earlier one at least 15 cm and 15 degrees away) and views
# that share no surface.
# A candidate is **right** when its views overlap (30 % of the points or more, at the true
# pose) and the dense alignment ends within 10 cm of the truth, **wrong** otherwise: a revisit
# aligned wrongly is as false a loop as two different places. Two statistics are now relative
# to what the frames can show: the dense check counts paired points per point that the old
# view holds at the found pose (not per point of the new view), and the photometric share
# asked for falls with the angle between the views, after the exposure change is taken off.
# 320x240 frames and every other offset return, to keep the lesson short.

# %%
if REAL is not None:
    from kintinuous_ref.loop_closure import calibration

    maker = calibration.KeyframeMaker(REAL, kitchen_truth, 320, 240, settings)
    rng = np.random.default_rng(0)
    calibrated = calibration.there_and_back_candidates(maker, 6, settings, rng)
    offsets = calibration.offset_pairs(kitchen_truth, 0.15, 15.0, 30, 10)[::2]  # every other
    calibrated += calibration.measure_pairs("offset return", maker, offsets, settings, rng)
    apart = calibration.apart_pairs(maker, list(range(0, 300, 20)), 3, settings)
    calibrated += calibration.measure_pairs("views apart", maker, apart, settings, rng)
    calibration.draw_distributions(calibrated, settings)
    plt.show()
    right = [c for c in calibrated if c.group == "right"]
    wrong = [c for c in calibrated if c.group == "wrong"]
    offset_right = [c for c in right if c.kind == "offset return"]
    print(
        f"{len(right)} right candidates ({len(offset_right)} offset returns), "
        f"{sum(c.verdict.accepted for c in right)} accepted; "
        f"{len(wrong)} wrong, {sum(c.verdict.accepted for c in wrong)} accepted"
    )
    assert calibration.SAME_PLACE == 0.3 and calibration.RIGHT_POSE == 0.1  # the labels above
    assert all(c.apart_deg >= 15 and c.apart_m >= 0.15 for c in offset_right)
if REAL is not None and REAL.is_redkitchen:
    absolute = min(c.verdict.icp_inlier_share for c in offset_right)
    relative = min(c.verdict.icp_overlap_share for c in offset_right)
    print(
        f"offset returns: paired per point down to {absolute:.2f}, per visible point {relative:.2f}"
    )
    assert len(offset_right) >= 3
    assert not any(c.verdict.accepted for c in wrong)  # no false loop
    assert sum(c.verdict.accepted for c in right) >= 2 / 3 * len(right)
    assert any(c.verdict.accepted for c in offset_right)  # 15 cm and 15 degrees off, closed
    assert len(wrong) >= 6 and any(c.kind == "views apart" for c in wrong)
    # The old absolute share (0.5) refuses offset returns that the relative one keeps.
    assert absolute < 0.5 and relative > settings.min_icp_overlap_share

# %% [markdown]
# ## Summary
#
# - Place recognition needs more than appearance and sparse geometry: two identical bays pass
#   both; the dense alignment's photometric agreement (the walls around them differ) does not.
# - The checks' thresholds are calibrated on real revisits with a known truth, relative to what
#   the two views can show (their overlap at the found pose, the angle between them), so that
#   returns 15 cm and 15 degrees off close while no wrong alignment passes (on the real frames,
#   where they are at hand).
# - The pose graph spreads a loop's error over the odometry edges, and dynamic covariance
#   scaling weights a loop that contradicts the rest down, so a false loop does not fold the
#   map. (The package also tests each new loop for consistency with the loops kept so far;
#   this lesson does not show it.)
# - A loop measures only the sum of the odometry errors between its ends; the edges'
#   covariances decide where the graph puts it, right only when they say where the tracker
#   was weak.
# - A loop's own covariance comes from its dense alignment's final system (J^T W J in units of
#   each term's noise, moved into the pose graph's residual by the adjoint), scaled to the few
#   effective pairs that real alignments are worth (`place_recognition.loop_covariance`,
#   calibrated against the ground truth in docs/loop_closure.md; not computed in this lesson).
# - The deformation graph bends the map as rigidly and smoothly as its pinned points allow; its
#   energy is minimised with damped steps, as plain Gauss-Newton diverges where nodes lie on a
#   line.
# - In a full run (`kintinuous reconstruct DATASET --out DIR --loop-closure`) the three work
#   together. After a closure the tracker keeps its moving volume and its coordinates; the
#   corrections so far make a running offset that takes its poses into corrected ones, and
#   the map, left in the tracker's coordinates, is deformed once at the end. What that does to
#   the ATE and to the start of the `revisit` lap, fused twice without loop closure, is
#   measured in docs/loop_closure.md with `benchmarks/loop_closure_runs.py` (a full run is too
#   long for a lesson).
#
# ## Exercises
#
# 1. **Tolerance.** Lower `min_photometric_share` until the twins' false loop is accepted: at
#    what share does it pass? Check: `check_exercise_1(share)` with the verdict's
#    `photometric_share`.
# 2. **Where to pin.** Pin only the two ends of the bent sheet (not its middle): how far from
#    flat does the middle stay, and why (think of E_reg)?
# 3. **A weaker loop.** Give the true loop edge of section 2 a sigma of 10 cm instead of 1 cm:
#    how much of the drift does it still remove?
# 4. **How weak is weak.** Declare edge 15 weak along x with a sigma of 5 cm instead of 30 cm:
#    what share of the 5 cm slide does the graph put on it? Compare with the share of its
#    variance in the sum of the variances along the loop (29 edges and the loop itself).


# Your answer goes into the next cell (`None` until you have it); the check cell compares it with
# the twins' verdict above and verifies that the loop passes below it, and says if it is open.

# %%
your_share = None  # exercise 1: the photometric share at which the false loop passes


# %%
def check_exercise_1(share: float | None) -> None:
    if share is None:
        print("exercise 1: not answered yet (fill in your_share above)")
        return
    assert abs(share - false_loop.photometric_share) < 1e-3, "the twins' photometric share"
    loose = LoopClosureConfig(min_photometric_share=false_loop.photometric_share - 1e-6)
    assert place_recognition.verify(bay2, bay1, loose, np.random.default_rng(0)).reason in (
        "implausible correction",
        "",
    ), "below it the photometric check passes (the plausibility gate still refuses 5 m)"
    print("exercise 1 correct")


check_exercise_1(your_share)
