"""design: Pareto optimisation of the head's mechanical layout (paper, section 2).

Seven minimised criteria over the 3D positions of camera and motors; the chosen head is written
as chosen_head.toml, which kinematics, the twin and the runtime load. (Built by the design issue.)
"""
