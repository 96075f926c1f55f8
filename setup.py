"""The build's one addition to pyproject.toml: the optional compiled SRG kernel.

``optional=True``: where the C compiler or the Python headers are missing, the build goes
on without it and :mod:`agent.srg.kernel` runs in pure Python (same results, slower).
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("agent.srg._kernel", ["agent/srg/_kernel.c"], optional=True)])
