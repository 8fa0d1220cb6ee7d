/PROG  PROG
/ATTR
OWNER		= MNEDITOR;
COMMENT		= "campaign";
PROG_SIZE	= 0;
FILE_NAME	= PROG;
VERSION		= 0;
LINE_COUNT	= 43;
MEMORY_SIZE	= 0;
PROTECT		= READ_WRITE;
TCD:  STACK_SIZE	= 0,
      TASK_PRIORITY	= 50,
      TIME_SLICE	= 0,
      BUSY_LAMP_OFF	= 0,
      ABORT_REQUEST	= 0,
      PAUSE_REQUEST	= 0;
DEFAULT_GROUP	= 1,*,*,*,*;
CONTROL_CODE	= 00000000 00000000;
/MN
   1:  ! stops 0..8 of 9 ;
   2:  ! stop 0 pose 717766 ;
   3:J P[1] 50% FINE    ;
   4:  WAIT 2.00(sec) ;
   5:  DO[1]=PULSE,0.2sec ;
   6:  WAIT 3.00(sec) ;
   7:  ! stop 1 validation 810039 ;
   8:J P[2] 50% FINE    ;
   9:  WAIT 2.00(sec) ;
  10:  DO[1]=PULSE,0.2sec ;
  11:  WAIT 3.00(sec) ;
  12:  ! stop 2 drift 717766 ;
  13:J P[3] 50% FINE    ;
  14:  WAIT 2.00(sec) ;
  15:  DO[1]=PULSE,0.2sec ;
  16:  WAIT 3.00(sec) ;
  17:  ! stop 3 pose 895608 ;
  18:J P[4] 50% FINE    ;
  19:  WAIT 2.00(sec) ;
  20:  DO[1]=PULSE,0.2sec ;
  21:  WAIT 3.00(sec) ;
  22:  ! stop 4 via 819166 ;
  23:J P[5] 50% FINE    ;
  24:  ! stop 5 pose 819166 ;
  25:J P[6] 50% FINE    ;
  26:  WAIT 2.00(sec) ;
  27:  DO[1]=PULSE,0.2sec ;
  28:  WAIT 3.00(sec) ;
  29:  ! stop 6 drift 717766 ;
  30:J P[7] 50% FINE    ;
  31:  WAIT 2.00(sec) ;
  32:  DO[1]=PULSE,0.2sec ;
  33:  WAIT 3.00(sec) ;
  34:  ! stop 7 repeat 1000895608 ;
  35:J P[8] 50% FINE    ;
  36:  WAIT 2.00(sec) ;
  37:  DO[1]=PULSE,0.2sec ;
  38:  WAIT 3.00(sec) ;
  39:  ! stop 8 pose 819104 ;
  40:J P[9] 50% FINE    ;
  41:  WAIT 2.00(sec) ;
  42:  DO[1]=PULSE,0.2sec ;
  43:  WAIT 3.00(sec) ;
/POS
P[1]{
   GP1:
	UF : 0, UT : 1,
	J1=    0.0000 deg,	J2=   35.8000 deg,	J3=  -69.5500 deg,
	J4=  -14.1429 deg,	J5=   49.0000 deg,	J6=   54.0000 deg
};
P[2]{
   GP1:
	UF : 0, UT : 1,
	J1=   19.7647 deg,	J2=   57.4000 deg,	J3=  -69.5500 deg,
	J4=  -70.7143 deg,	J5=   16.3333 deg,	J6=  162.0000 deg
};
P[3]{
   GP1:
	UF : 0, UT : 1,
	J1=    0.0000 deg,	J2=   35.8000 deg,	J3=  -69.5500 deg,
	J4=  -14.1429 deg,	J5=   49.0000 deg,	J6=   54.0000 deg
};
P[4]{
   GP1:
	UF : 0, UT : 1,
	J1=   39.5294 deg,	J2=   57.4000 deg,	J3=  -21.3500 deg,
	J4= -127.2857 deg,	J5=   49.0000 deg,	J6=  126.0000 deg
};
P[5]{
   GP1:
	UF : 0, UT : 1,
	J1=   29.6471 deg,	J2=   68.2000 deg,	J3=  -33.4000 deg,
	J4= -127.2857 deg,	J5=   49.0000 deg,	J6=   90.0000 deg
};
P[6]{
   GP1:
	UF : 0, UT : 1,
	J1=   19.7647 deg,	J2=   79.0000 deg,	J3=  -45.4500 deg,
	J4= -127.2857 deg,	J5=   49.0000 deg,	J6=   54.0000 deg
};
P[7]{
   GP1:
	UF : 0, UT : 1,
	J1=    0.0000 deg,	J2=   35.8000 deg,	J3=  -69.5500 deg,
	J4=  -14.1429 deg,	J5=   49.0000 deg,	J6=   54.0000 deg
};
P[8]{
   GP1:
	UF : 0, UT : 1,
	J1=   39.5294 deg,	J2=   57.4000 deg,	J3=  -21.3500 deg,
	J4= -127.2857 deg,	J5=   49.0000 deg,	J6=  126.0000 deg
};
P[9]{
   GP1:
	UF : 0, UT : 1,
	J1=   19.7647 deg,	J2=   79.0000 deg,	J3=  -45.4500 deg,
	J4= -155.5714 deg,	J5=   49.0000 deg,	J6=  -18.0000 deg
};
/END
