"""Expression transfer between faces with 3D thin-plate splines (Erdoğdu, chapters 4-5)."""
