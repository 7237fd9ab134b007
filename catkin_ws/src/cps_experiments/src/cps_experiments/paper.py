"""The paper's numbers, written down once (Kivrak et al., Tables 2-6, section 5, Fig. 13).

Robot names are our fleet's: scout = Scout 2.0 (type A, 3D lidar), jackal = Jackal (type B,
depth camera), champ = the legged robot, iris = the aerial robot (both depth cameras).
"""

from cps_bw_manager.table6 import PAPER_TABLE6, TABLE6_FINISHED_BY_STEP, TABLE6_ROBOTS  # noqa: F401

# Table 4 (voxel 10 cm; the text: Scout 1 cm): MB/s (min, max) raw, filtered, compressed, and Hz.
TABLE4 = {
    "scout": ((2.85, 4.50), (2.1, 2.69), (0.37, 0.46), 10),
    "jackal": ((280.0, 290.0), (22.14, 22.57), (4.12, 4.44), 30),
    "champ": ((280.0, 290.0), (10.32, 12.47), (1.67, 2.47), 30),
    "iris": ((280.0, 290.0), (10.53, 12.64), (1.8, 2.7), 30),
}
TABLE4_TOTAL = ((842.85, 874.50), (45.09, 50.37), (8.01, 10.07))
# Section 5: raw -> filtered (10 cm) -> compressed, MB/s (averages quoted in the text).
FLEET_RAW_MBYTES_PER_S = 874.50
FLEET_FILTERED_MBYTES_PER_S = 44.55
FLEET_COMPRESSED_MBYTES_PER_S = 8.71
# Table 3: the whole fleet's maximum incl. joint states and odometry.
TABLE3_FLEET_MAX_MBYTES_PER_S = 874.659

# Table 5: fleet -> (bandwidth avg, max, std MB/s), (latency avg, max, std ms).
TABLE5 = {
    ("scout",): ((1.195, 1.65, 0.27), (39.0, 42.0, 28.0)),
    ("scout", "jackal"): ((4.70, 4.74, 0.01), (41.0, 45.0, 28.0)),
    ("scout", "jackal", "iris"): ((5.3, 5.67, 0.12), (43.0, 58.0, 39.0)),
    ("scout", "jackal", "iris", "champ"): ((4.80, 6.57, 3.02), (52.0, 65.0, 9.71)),
}
TABLE5_LATENCY_BOUND_MS = 100.0

# Fig. 13 / section 5: per-robot data rates without management and the deployable counts at 60 Mbit/s.
FIG13_TYPE_A_MBYTES_PER_S = 0.46  # 3.68 Mbit/s, Scout's compressed max (Table 4)
FIG13_TYPE_B_MBYTES_PER_S = 3.13  # 25.04 Mbit/s, the average of Jackal, legged and aerial
FIG13_LINK_MBPS = 60.0
FIG13_DEPLOYABLE_A = 16
FIG13_DEPLOYABLE_B = 2

# The link (2.4.1, 2.4.4).
LINK_MBPS = 60.0
RESERVE_FRACTION = 0.04
