"""scene_worker."""
