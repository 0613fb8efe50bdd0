"""Motion skills tasks compose: phases with their costs, built from plans (gait, reaches, grasps)."""
