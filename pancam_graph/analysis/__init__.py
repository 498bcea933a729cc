"""The dissertation's Chapter 3 error model as a tool: closed-form covariance of stereo points, of
two-stop visual odometry and its growth over many stops, of the HRC + left-WAC pair, and of the
two-site bundle adjustment behind Table 3.2; GTSAM equivalents to check them against."""
