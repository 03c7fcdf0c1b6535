"""Input and output: capture folders, images, normal-map encodings, reports."""
