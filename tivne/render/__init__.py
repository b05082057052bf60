"""The render path, in stage order: rays (View -> RayBundle), samplers (pixels; samples along rays),
renderer (field at the samples -> composited rays; the one ``render_pixels`` of the system), losses."""
