"""ROS-native outputs of a tracked subject: its URDF (`urdf`) and TF frames (`tf`)."""
