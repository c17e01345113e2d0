"""Using trained models: prediction on new images, export (ONNX, TorchScript, int8),
int8 quantisation and the inference benchmark."""
