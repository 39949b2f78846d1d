"""The paper's front end: laser line and corner fits, sonar processing, sonar-aided
segmentation and laser-sonar fusion, turning each scan into features with covariances."""
