"""Layer 5: files: .vdb (write, info), VTK image data / poly data / meshes, printable meshes of a
zero set, preview images and the HTML report."""
