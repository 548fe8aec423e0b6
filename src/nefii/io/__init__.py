"""Reading and writing files: images, atomic outputs."""
