"""runtime.vision2d: the paper's 2D visual competences (section 3): stabilisation, tracking."""
