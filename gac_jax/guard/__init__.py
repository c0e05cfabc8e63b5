"""The accuracy guard: does a runtime / precision keep float32's model? Its statistics, its
rules for the detector (detector_rule) and the depth network (depth_rule), and the verdict file
(verdict_file) bound to the exported model."""
