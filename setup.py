"""The build's one addition to pyproject.toml: the optional compiled kernels.

``optional=True``: where the C compiler or the Python headers are missing, the build goes
on without them and :mod:`agent.srg.kernel`, the pose decoder
(:func:`schemas.codec.decode_pose`), the answer reader
(:func:`agent.protocol.query.pose_from_wire`), the dead reckoner
(:mod:`services.accel_rig.integrator`), the marker segmentation
(:mod:`services.outside_in.blobs`) and the outside-in pose fit (:mod:`services.outside_in.pose`)
run in pure Python (same results, slower; the fit's to rounding).  The pose
decoder, the answer reader, the dead reckoner's step and the segmentation are compiled
without floating-point contraction, so that their arithmetic rounds as Python's does.

A kernel that fails to build also loses the copy an earlier build left beside its source
(an editable install's): that copy was built from other source, and loading it would call
the new Python with the old kernel's signatures.
"""

from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


class BuildExt(build_ext):
    """``build_ext`` that removes an optional kernel's stale in-tree copy when it fails."""

    def build_extension(self, ext: Extension) -> None:
        try:
            super().build_extension(ext)
        except Exception:
            if ext.optional:
                Path(self.get_ext_filename(ext.name)).unlink(missing_ok=True)
            raise


setup(cmdclass={"build_ext": BuildExt}, ext_modules=[
    Extension("agent.srg._kernel", ["agent/srg/_kernel.c"], optional=True),
    Extension("agent.protocol._wire", ["agent/protocol/_wire.c"], optional=True,
              extra_compile_args=["-ffp-contract=off"]),
    Extension("schemas._pose", ["schemas/_pose.c"], optional=True,
              extra_compile_args=["-ffp-contract=off"]),
    Extension("services.accel_rig._step", ["services/accel_rig/_step.c"], optional=True,
              extra_compile_args=["-ffp-contract=off"]),
    Extension("services.outside_in._blobs", ["services/outside_in/_blobs.c"], optional=True,
              extra_compile_args=["-ffp-contract=off"]),
    Extension("services.outside_in._fit", ["services/outside_in/_fit.c"], optional=True),
])
