"""Place recognition: vocabulary trees (k-means, BIRCH), the image database, loop detection."""
