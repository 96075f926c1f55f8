"""The build's one addition to pyproject.toml: the optional compiled kernels.

``optional=True``: where the C compiler or the Python headers are missing, the build goes
on without them and :mod:`agent.srg.kernel`, the pose decoder
(:func:`schemas.codec.decode_pose`), the answer reader
(:func:`agent.protocol.query.pose_from_wire`), the dead reckoner
(:mod:`services.accel_rig.integrator`), the marker segmentation
(:mod:`services.outside_in.blobs`), the outside-in pose fit (:mod:`services.outside_in.pose`),
the fiducial tracker's fits and edge crossings (:mod:`services.fiducials.pose`,
:mod:`services.fiducials.edges`) and the laser tracker's labelings, frames, installation
covariances and moves and its installation estimate's update (:mod:`services.laser_camera.pose`,
:mod:`services.laser_camera.tracker`, :mod:`services.laser_camera.installation_estimate`) run
in pure Python (same results, slower; the fits' and the laser kernels' to rounding).  The
pose decoder, the answer reader, the dead reckoner's step, the segmentation, the fiducial
and the laser kernels are compiled without floating-point contraction, so that their
arithmetic rounds as Python's does.

A kernel that fails to build also loses the copy an earlier build left beside its source
(an editable install's): that copy was built from other source, and loading it would call
the new Python with the old kernel's signatures.

Each kernel is compiled with the SHA-256 of its source and of the init all kernels share
(``schemas/_twin.h``) (``UMA_SOURCE_HASH``, the module's ``SOURCE_HASH``):
:func:`schemas.native.compiled_twin` runs a kernel only where that hash is the one of the
``.c`` file beside it and the header (shipped as package data), so a copy built from older
source is never used.
"""

import hashlib
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


def twin(name: str, contract: bool = True) -> Extension:
    """The optional kernel ``name`` (a dotted module, its source ``name``.c), built with the
    hash of that source (the same as :func:`schemas.native.source_hash`) and the module init
    all twins share (``schemas/_twin.h``); ``contract=False`` compiles it without
    floating-point contraction."""
    source = name.replace(".", "/") + ".c"
    root = Path(__file__).parent
    digest = hashlib.sha256((root / source).read_bytes()
                            + (root / "schemas" / "_twin.h").read_bytes()).hexdigest()
    return Extension(name, [source], optional=True, include_dirs=["schemas"],
                     depends=["schemas/_twin.h"],
                     define_macros=[("UMA_SOURCE_HASH", f'"{digest}"')],
                     extra_compile_args=[] if contract else ["-ffp-contract=off"])


setup(cmdclass={"build_ext": BuildExt}, ext_modules=[
    twin("agent.srg._kernel"),
    twin("agent.protocol._wire", contract=False),
    twin("schemas._pose", contract=False),
    twin("services.accel_rig._step", contract=False),
    twin("services.outside_in._blobs", contract=False),
    twin("services.outside_in._fit"),
    twin("services.fiducials._kernels", contract=False),
    twin("services.laser_camera._kernels", contract=False),
])
