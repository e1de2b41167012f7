"""The closed lists of words the system accepts, each written once.

The configuration's checks (config.py), the command line's choices (program/cli.py), the
trackers (odometry/) and the tests all read them here. This module imports nothing, so that
any of them, `kintinuous --help` included, can read a list without importing NumPy or another
module of the package (and without an import circle: config.py checks the words of odometry's
settings, and odometry imports config.py).
"""

# Odometry (paper IV, V; odometry/__init__.py says what each method is).
METHODS = ("icp", "rgbd", "fovis", "fovis/icp", "fovis/rgbd", "icp+rgbd", "fovis/icp+rgbd")
DENSE_METHODS = ("icp", "rgbd", "icp+rgbd")  # the trackers that need no FOVIS
DEFAULT_METHOD = "icp+rgbd"  # the paper's tracker
# The pipeline's extra choice: the dataset's ground-truth poses instead of a tracker.
GROUNDTRUTH = "groundtruth"
ODOMETRY_CHOICES = (GROUNDTRUTH, *METHODS)

# combined.weighting: how `icp+rgbd` weighs its two terms (odometry/combined.py).
WEIGHTINGS = (
    "paper",
    "paper-metres",
    "original-code",
    "elasticfusion",
    "information",
    "degeneracy-aware",
    "huber",
    "tukey",
)
# The weightings that are "degeneracy-aware" with a robust kernel on the ICP rows.
ROBUST_WEIGHTINGS = ("huber", "tukey")

# icp.robust_kernel: the M-estimator of the ICP residuals (odometry/icp.py); "none" is least
# squares. The fast backends pass a kernel as its index in this tuple.
ROBUST_KERNELS = ("none", "huber", "tukey")

# tracking.fallback: a failed frame's pose (odometry/__init__.py).
FALLBACKS = ("constant-velocity", "previous")
# How the FOVIS switching strategy measures a disagreement of two translations: "length" the
# paper's | ||t_fovis|| - ||t_other|| |, "vector" ||t_fovis - t_other|| (which also sees two
# motions of one length in different directions)
SWITCH_RULES = ("length", "vector")

# volume.placement: where the volume sits relative to the first camera (tsdf.volume_origin).
PLACEMENTS = ("ahead", "centred")

# rgbd.gradient: the image gradient in the RGB-D Jacobian (odometry/rgbd.py).
GRADIENTS = ("current", "warped")

# The command line's --backend: the reference, the fast package's two, or the first that runs
# here (backend.load_backend).
BACKENDS = ("ref", "cpu", "cuda")  # the project's own, named even where one is not installed
BACKEND_CHOICES = (*BACKENDS, "auto")

# The TUM RGB-D sequences known by name (datasets/download.py holds their archives): those of the
# paper's Table I, then others.
PAPER_SEQUENCES = ("fr1/desk", "fr2/desk", "fr1/room", "fr2/large_no_loop")
OTHER_SEQUENCES = ("fr1/xyz", "fr1/360", "fr2/xyz", "fr3/long_office_household")
