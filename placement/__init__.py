"""placement: where on the body to wear the camera (paper, section 2.1, Fig. 3).

Body model of ~1800 polygons in 16 rotatable segments; field of view, handling-space view and
motion resilience per polygon; body maps and the Head/Shoulder/Chest table. (Built by the
placement issue.)
"""
