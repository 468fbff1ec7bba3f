"""Waymo Open Motion Dataset I/O: GPUDrive's processed JSON (`gpudrive_json`), TFRecord framing
(`tfrecord`), the protobuf wire format (`protowire`) and the Scenario message (`scenario_proto`)."""
