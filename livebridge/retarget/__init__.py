"""Expression transfer between faces: landmarks, control points and 3D thin-plate splines."""
