"""Selmanaj, Corno, Panzani, Savaresi (2017), "Vehicle sideslip estimation: a kinematic based
approach", Control Engineering Practice 67 (shared/papers/selmanaj2017-kinematic-sideslip-
observer.md): ``kinematic_heuristic`` (the observer, eq. 5-7) and ``wheel_speed`` (Vx from
the compensated wheel speeds, section 2.3). Its pre-processing blocks (CoG translation, roll
and gravity, online offsets) are shared by every method and live in ``estimators.common``."""
