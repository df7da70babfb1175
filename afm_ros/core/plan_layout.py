"""Layout of the packed scan plan handed to the integration kernel (a float64 array; see
:meth:`afm_ros.core.scanner.ScanPlan.packed`). Its own module so that the scanner and the
imperfection models can both use it."""

PLAN_ACTIVE, PLAN_START, PLAN_X_LEFT, PLAN_SIZE_X, PLAN_Y_FIRST, PLAN_LINE_STEP, PLAN_LINE_RATE, PLAN_LINES, \
    PLAN_CONTINUOUS, PLAN_PARK_X, PLAN_PARK_Y = range(11)
PLAN_LENGTH = 11
