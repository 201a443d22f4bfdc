"""Expression transfer between faces (Erdogdu, chapters 4-5): landmark sets and 3D thin-plate splines."""
