"""Map merging (thesis chapter 8): features, correspondences, validated transforms, fusion.

Entry points: merge_pair (two maps), merge_all (Figure 35, many maps), merge_files (offline tool).
"""

from .hints import Hint
from .multi import GlobalMergeResult, merge_all
from .offline import merge_files, merge_grids
from .pair import MergeResult, merge_pair
from .params import VARIANTS, MergeParams, coopd_params, features_params, rigid_params, thesis_params

__all__ = [
    "GlobalMergeResult", "Hint", "MergeParams", "MergeResult", "VARIANTS",
    "coopd_params", "features_params", "merge_all", "merge_files", "merge_grids", "merge_pair",
    "rigid_params", "thesis_params",
]
