"""Record an episode with a task, stop (save) it, and list the dataset's episodes."""
import sys
import time

from phone2act import Client

with Client(sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:50051") as client:
    client.episodes.start("pick up the ball and put it in the basket")
    time.sleep(1.0)  # teleop or a policy would drive the arm here
    saved = client.episodes.stop()
    print(f"saved episode {saved.episode_index}: {saved.length_frames} frames")
    for ep in client.episodes.list():
        print(ep.episode_index, repr(ep.task), ep.length_frames, f"{ep.duration_s:.2f} s")
