// Empty unit: the target amalgam_pch exists to compile the shared precompiled header (the
// root CMakeLists.txt, AMALGAM_PCH) that the libraries and programs reuse.
