"""The spatial relationship graph alone: no agent, no network, plain numpy.

    python examples/offline_srg.py
"""

import numpy as np

from agent import Graph
from agent import geometry as geo

g = Graph(buffer_s=10.0)
# a calibrated camera: static, valid at all times
g.add_static("ivy/world", "cam/nw", [1.2, 1.2, 1.2], geo.rotvec_to_quat([0.0, 0.0, np.pi]))
# a tracked head at 100 Hz for one second
for k in range(100):
    g.add_measurement("ivy/world", "alice/head", k * 10_000_000, [0.0, 0.01 * k, 1.6],
                      [0.0, 0.0, 0.0, 1.0], frequency_hz=100, latency_s=0.005, pos_std_m=0.002)

r = g.pose("cam/nw", "alice/head", at=505_000_000, error="hops")  # between two samples
print("head in the camera's frame at 0.505 s:", np.round(r.position, 4))
print("path:", " -> ".join(r.path))
print("position std (m):", np.round(np.sqrt(np.diag(r.covariance)[:3]), 4))
