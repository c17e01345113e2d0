"""The seed paper's published figures (Eljarida et al., *Instant Particle Size Distribution
Measurement Using CNNs Trained on Synthetic Data*): its Table 2 (accuracy on its 933 synthetic
test renders, GPU inference) and Table 3 (inference speed on a laptop), for the report to put
this project's figures beside. Written once here; nothing else holds them."""

from __future__ import annotations

# Table 2: per target, (R², MSE mm², MAE mm); its own test set: 933 renders of 1,000-1,350
# crushed-rock particles on a 300 mm table at 512 px, labels of mean ± sd d10 2.55 ± 0.88,
# d50 7.31 ± 1.29, d90 12.01 ± 1.11 mm
TABLE2 = {
    "resnet50": {"d10": (0.9591, 0.0315, 0.0913), "d50": (0.9904, 0.0160, 0.0747), "d90": (0.9888, 0.0137, 0.0660),
                 "overall": (0.9987, 0.0204, 0.0773)},
    "inception_v3": {"d10": (0.8933, 0.0821, 0.2212), "d50": (0.9738, 0.0438, 0.1651),
                     "d90": (0.9680, 0.0391, 0.1525), "overall": (0.9966, 0.0550, 0.1796)},
    "efficientnet_b0": {"d10": (0.8777, 0.0941, 0.2357), "d50": (0.9667, 0.0555, 0.1841),
                        "d90": (0.9604, 0.0484, 0.1721), "overall": (0.9959, 0.0660, 0.1973)},
}
TABLE2_TEST = "933 renders of its own distribution (5,000 scenes: 1,000-1,350 particles, 300 mm, 512 px)"

# Table 3: images per second on an RTX 3060 GPU and an 8-core AMD Ryzen 7 5800H CPU, parameters (M)
TABLE3 = {
    "resnet50": {"gpu_fps": 27.31, "cpu_fps": 14.66, "params_m": 25.6},
    "inception_v3": {"gpu_fps": 23.18, "cpu_fps": 12.00, "params_m": 23.9},
    "efficientnet_b0": {"gpu_fps": 37.75, "cpu_fps": 21.51, "params_m": 5.3},
}
TABLE3_CPU = "AMD Ryzen 7 5800H, 8 cores"
TABLE3_GPU = "NVIDIA RTX 3060"
