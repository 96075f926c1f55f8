"""The build's one addition to pyproject.toml: the optional compiled kernels.

``optional=True``: where the C compiler or the Python headers are missing, the build goes
on without them and :mod:`agent.srg.kernel` and the dead reckoner
(:mod:`services.accel_rig.integrator`) run in pure Python (same results, slower).  The
dead reckoner's step is compiled without floating-point contraction, so that its vector
arithmetic rounds as Python's does.
"""

from setuptools import Extension, setup

setup(ext_modules=[
    Extension("agent.srg._kernel", ["agent/srg/_kernel.c"], optional=True),
    Extension("services.accel_rig._step", ["services/accel_rig/_step.c"], optional=True,
              extra_compile_args=["-ffp-contract=off"]),
])
