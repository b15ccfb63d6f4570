"""Run control (cancellation, progress): :mod:`skyroute.stages.control` is its one home (the
stages poll it); this name is the same module object, kept for API stability."""

import sys

from skyroute.stages import control as _control

sys.modules[__name__] = _control
