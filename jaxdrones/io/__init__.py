"""Files a user keeps: plots (`plotting`), videos (`video`), run folders, provenance and the compilation cache
(`runs`)."""
