"""The geometry stage for data without a mesh: a NeuS signed distance field learned from the images
(paper Sec. 3.1: pretrained, then frozen), its mesh, and sphere tracing of it."""
