"""Layout of the packed scan plan handed to the integration kernel (a float64 array; see
:meth:`afm_ros.core.scanner.ScanPlan.packed`). Its own module so that the scanner and the
imperfection models can both use it (and the nodes' topic helpers, without numba)."""

(
    PLAN_ACTIVE,
    PLAN_START,
    PLAN_X_LEFT,
    PLAN_SIZE_X,
    PLAN_Y_FIRST,
    PLAN_LINE_STEP,
    PLAN_LINE_RATE,
    PLAN_LINES,
    PLAN_CONTINUOUS,
    PLAN_PARK_X,
    PLAN_PARK_Y,
    PLAN_ROTATED,
    PLAN_CENTER_X,
    PLAN_CENTER_Y,
    PLAN_COS,
    PLAN_SIN,
) = range(16)
PLAN_LENGTH = 16

# ground truth of the imperfections (afm_ros.core.artefacts.truth), in the order of the truth topic
TRUTH_KEYS = (
    "hysteresis_x",
    "hysteresis_y",
    "creep_x",
    "creep_y",
    "drift_x",
    "drift_y",
    "drift_z",
)
