"""Motion-mask providers (config group ``masks``): base (interface, dataset, none), folder,
geometric (model-free), maskrcnn (optional torchvision)."""
