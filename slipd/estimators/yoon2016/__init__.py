"""Yoon, Li, Ahn (2016), "Estimation of vehicle sideslip angle and tire-road friction
coefficient based on magnetometer with GPS", Int. J. Automotive Technology 17(3)
(shared/papers/yoon2016-magnetometer-gps-sideslip-friction.txt): three filters in cascade,
``heading`` (the heading EKF with the magnetometer and its calibration), ``sideslip`` (the
GNSS-velocity KF with delay compensation) and ``friction`` (the brush-tyre friction EKF),
run by the method ``gnss_magnetometer`` on one state vector (``state.LAYOUT``)."""
