"""What a training run says about itself: its status file, running statistics, metrics log and dashboard."""
