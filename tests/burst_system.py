"""The coupled 2-state, 2-row system the numerical fuzz found (round 15): after a loss burst its several-row updates
cancel like ‖P‖² (kalman.burst_limit), and after a long one its prior is singular to working precision. Shared by
the tests that hold every estimator to the core's rescue on it."""

import numpy as np

A = np.array([[0.7295, 0.8567], [1.046, 0.5705]])
C = np.array([[2.0939, 0.7043], [0.8812, 0.5822]])
Q = np.array([[0.5746, -0.6109], [-0.6109, 1.5627]])
R = np.array([[2.5394, -2.0212], [-2.0212, 2.4948]])
BURST = dict(A=A, C=C, Q=Q, R=R)
