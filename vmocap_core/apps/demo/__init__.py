"""`vmocap demo`: the whole pipeline on real videos (Pose2Sim's Demo_SinglePerson); see cli.py."""
