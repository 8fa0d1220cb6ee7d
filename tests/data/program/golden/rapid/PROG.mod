MODULE PROG
  ! COMAU Racer5-0.80: stops 0..8 of 9, joints in deg (controller convention); written by `campaign program --format rapid`
  CONST jointtarget S0:=[[0.0000,35.8000,-69.5500,-14.1429,49.0000,54.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S1:=[[19.7647,57.4000,-69.5500,-70.7143,16.3333,162.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S2:=[[0.0000,35.8000,-69.5500,-14.1429,49.0000,54.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S3:=[[39.5294,57.4000,-21.3500,-127.2857,49.0000,126.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S4:=[[29.6471,68.2000,-33.4000,-127.2857,49.0000,90.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S5:=[[19.7647,79.0000,-45.4500,-127.2857,49.0000,54.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S6:=[[0.0000,35.8000,-69.5500,-14.1429,49.0000,54.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S7:=[[39.5294,57.4000,-21.3500,-127.2857,49.0000,126.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  CONST jointtarget S8:=[[19.7647,79.0000,-45.4500,-155.5714,49.0000,-18.0000],[9E9,9E9,9E9,9E9,9E9,9E9]];
  PROC main()
    VelSet 50.0, 5000;
    AccSet 50.0, 100;
    ! stop 0 pose 717766
    MoveAbsJ S0\NoEOffs, v1000, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 1 validation 810039
    MoveAbsJ S1\NoEOffs, v1000\T:=1.150, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 2 drift 717766
    MoveAbsJ S2\NoEOffs, v1000\T:=1.150, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 3 pose 895608
    MoveAbsJ S3\NoEOffs, v1000\T:=1.365, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 4 via 819166
    MoveAbsJ S4\NoEOffs, v1000\T:=0.772, fine, tool0;
    ! stop 5 pose 819166
    MoveAbsJ S5\NoEOffs, v1000\T:=0.772, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 6 drift 717766
    MoveAbsJ S6\NoEOffs, v1000\T:=1.365, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 7 repeat 1000895608
    MoveAbsJ S7\NoEOffs, v1000\T:=1.365, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
    ! stop 8 pose 819104
    MoveAbsJ S8\NoEOffs, v1000\T:=1.290, fine, tool0;
    WaitTime 2.000;
    PulseDO\PLength:=0.2, DO1;
    WaitTime 3.000;
  ENDPROC
ENDMODULE
