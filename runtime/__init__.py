"""runtime: what runs on (or for) the wearable: MonoSLAM, gaze control, 2D competences, the
MuJoCo twin, hardware drivers and the operator's station (paper, sections 3 to 5).
(Built by the twin, SLAM, gaze and 2D-competence issues.)
"""
