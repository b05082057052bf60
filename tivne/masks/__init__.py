"""Motion-mask providers (config group ``masks``): base (interface, dataset, none), folder,
geometric (model-free; its pure tests in seeds and segments), maskrcnn (optional torchvision)."""
