"""The gyro bias a simulated flight's IMU really had (deg/h, IMU frame).

Usage: .venv/bin/python scripts/gyro_bias_truth.py FLIGHT_DIR

The simulator draws the bias and does not write it down; this recovers it
from the flight itself: over each interval between two truth.csv poses, the
rotation the gyro samples of imu.csv integrate to, less the truth's rotation
(inertial frame, the Earth's rate included), per second, averaged over the
flight. Its noise is the gyro's angle random walk over the flight (about
1 deg/h over 60 s of the realistic scenarios; printed per interval as `sd`).
"""
import csv,sys,math
import numpy as np
d=sys.argv[1]
def q2m(w,x,y,z):
    return np.array([[1-2*(y*y+z*z),2*(x*y-w*z),2*(x*z+w*y)],[2*(x*y+w*z),1-2*(x*x+z*z),2*(y*z-w*x)],[2*(x*z-w*y),2*(y*z+w*x),1-2*(x*x+y*y)]])
cam=__import__('json').load(open(d+'/camera.json'))
qci=cam['q_cam_imu']; R_cam_imu=q2m(*qci)
tr=[list(map(float,r)) for r in list(csv.reader(open(d+'/truth.csv')))[1:]]
imu=np.array([list(map(float,r[:4])) for r in list(csv.reader(open(d+'/imu.csv')))[1:]])
we=7.292115e-5
def rotvec(R):
    c=(np.trace(R)-1)/2; a=math.acos(max(-1,min(1,c)))
    if a<1e-12: return np.zeros(3)
    return a/(2*math.sin(a))*np.array([R[2,1]-R[1,2],R[0,2]-R[2,0],R[1,0]-R[0,1]])
def ecef_rot(t):
    # rotation ECEF->inertial at time t about z
    a=we*t; c,s=math.cos(a),math.sin(a)
    return np.array([[c,-s,0],[s,c,0],[0,0,1]])
res=[]
for a,b in zip(tr[:-1],tr[1:]):
    t0,t1=a[0],b[0]
    R0=ecef_rot(t0)@q2m(*a[4:8])@R_cam_imu  # inertial<-imu  (q_ecef_cam * q_cam_imu)
    R1=ecef_rot(t1)@q2m(*b[4:8])@R_cam_imu
    true_rv=rotvec(R0.T@R1)  # body-frame rotation over interval
    sel=(imu[:,0]>t0+1e-9)&(imu[:,0]<=t1+1e-9)
    dt=np.diff(np.concatenate([[t0],imu[sel,0]]))
    # integrate gyro as small rotations
    R=np.eye(3)
    for w,h in zip(imu[sel,1:4],dt):
        th=w*h; n=np.linalg.norm(th)
        K=np.array([[0,-th[2],th[1]],[th[2],0,-th[0]],[-th[1],th[0],0]])
        R=R@(np.eye(3)+K*(math.sin(n)/n if n>0 else 1)+K@K*((1-math.cos(n))/n/n if n>0 else .5))
    meas=rotvec(R)
    res.append((meas-true_rv)/(t1-t0))
res=np.array(res)
print('truth gyro bias deg/h (IMU):', np.round(res.mean(0)*180/math.pi*3600,2), 'sd of interval means', np.round(res.std(0)*180/math.pi*3600,1))
