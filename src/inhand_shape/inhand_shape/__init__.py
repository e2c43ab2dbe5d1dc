"""Shape from the map: surface mesh, superquadric parts, the graspable part and its grasps."""
