"""How the map's features look and are found again in an image (paper, section 4.1), in one
place: a feature's patches (patch.py), the plane its patch lies on and the template it induces
for the current view (plane.py, warp.py), the one match score, zero-mean normalised
cross-correlation at every pixel of an ellipse with the one parabolic sub-pixel step (zncc.py),
the affine sub-pixel refinement (refine.py), the frame's active search over every feature and the
same search for one template (search.py), and the plane fitted to a feature's looks (normals.py).
The whole-image scans of relocalisation and of the target's re-acquisition use OpenCV's
``matchTemplate`` with the same score (``2 (1 - TM_CCOEFF_NORMED)``): over a whole image its
FFT beats a per-pixel correlation."""

from .patch import TEMPLATE_SIZE, extract_template, first_view_patch, match_noise_shape, patch_half
from .plane import local_plane_normal, warped_template
from .search import Match, match_features, search

__all__ = ["TEMPLATE_SIZE", "Match", "extract_template", "first_view_patch", "local_plane_normal", "match_features",
           "match_noise_shape", "patch_half", "search", "warped_template"]
