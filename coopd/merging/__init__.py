"""Map merging (thesis chapter 8): features, correspondences, validated transforms, fusion."""
