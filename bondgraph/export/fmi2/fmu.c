/* FMI 2.0 Model Exchange and Co-Simulation functions of a bondgraph model.
 *
 * Written by bondgraph (bondgraph/export/fmi2/fmu.c, copied unchanged into
 * every exported FMU). It includes "config.h" (the GUID) and "model.c" (the
 * model's C99 functions, bondgraph.core.codegen_c) and implements the FMI
 * 2.0 standard (Modelica Association 2014, FMI for Model Exchange and
 * Co-Simulation 2.0, sections 2, 3 and 4) for an ODE without events.
 *
 * Value references: parameters 0 .. N_THETA-1, states, their derivatives,
 * inputs, outputs, in this order (bondgraph.export.fmu writes the same
 * layout into modelDescription.xml).
 *
 * Co-simulation: fmi2DoStep integrates over the communication step with the
 * inputs held constant, by the embedded Runge-Kutta 5(4) pair of Dormand and
 * Prince (1980, J. Comput. Appl. Math. 6:19-26) with the step-size control of
 * Hairer, Norsett and Wanner (Solving ODEs I, 2nd ed., 1993, section II.4);
 * relative tolerance: the one given to fmi2SetupExperiment, else 1e-8.
 */

#include <float.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "config.h"
#include "model.c"

#define NX BG_N_X
#define NU BG_N_U
#define NP BG_N_THETA
#define NY BG_N_Y
#define DIM(n) ((n) > 0 ? (n) : 1)
#define VR_X (NP)
#define VR_DX (NP + NX)
#define VR_U (NP + 2 * NX)
#define VR_Y (NP + 2 * NX + NU)
#define VR_END (NP + 2 * NX + NU + NY)
#define MAX_STEPS 10000000L
/* what config.h adds to a failed step's message: the model's laws that jump */
#ifndef BG_STEP_HINT
#define BG_STEP_HINT ""
#endif

typedef struct {
    double theta[DIM(NP)], x[DIM(NX)], u[DIM(NU)];
    double time, tol, h;
    int cs;
    const fmi2CallbackFunctions *cb;
    char name[256];
} Inst;

static void logmsg(Inst *c, fmi2Status status, const char *msg)
{
    if (c && c->cb && c->cb->logger)
        c->cb->logger(c->cb->componentEnvironment, c->name, status,
                      status == fmi2OK ? "logAll" : "logStatusError", "%s", msg);
}

static fmi2Status bad_vr(Inst *c, fmi2ValueReference vr, const char *what)
{
    char buf[160];
    snprintf(buf, sizeof buf, "%s: value reference %u is not valid here", what, (unsigned)vr);
    logmsg(c, fmi2Error, buf);
    return fmi2Error;
}

/* ------------------------------------------------------------- common */
const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[])
{
    (void)c; (void)on; (void)n; (void)cats;
    return fmi2OK;
}

static void reset(Inst *c)
{
    memcpy(c->theta, BG_THETA0, sizeof(double) * (size_t)DIM(NP));
    memcpy(c->x, BG_X0, sizeof(double) * (size_t)DIM(NX));
    memcpy(c->u, BG_U0, sizeof(double) * (size_t)DIM(NU));
    c->time = 0.0;
    c->tol = 1e-8;
    c->h = 0.0;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid,
                              fmi2String location, const fmi2CallbackFunctions *cb,
                              fmi2Boolean visible, fmi2Boolean logging)
{
    (void)location; (void)visible; (void)logging;
    if (!cb || !cb->allocateMemory || !cb->freeMemory) return NULL;
    if (!guid || strcmp(guid, BG_GUID) != 0) {
        if (cb->logger)
            cb->logger(cb->componentEnvironment, name, fmi2Error, "logStatusError",
                       "GUID %s does not match %s", guid ? guid : "(null)", BG_GUID);
        return NULL;
    }
    Inst *c = (Inst *)cb->allocateMemory(1, sizeof(Inst));
    if (!c) return NULL;
    c->cb = cb;
    c->cs = type == fmi2CoSimulation;
    snprintf(c->name, sizeof c->name, "%s", name ? name : "");
    reset(c);
    return c;
}

void fmi2FreeInstance(fmi2Component c)
{
    Inst *s = (Inst *)c;
    if (s) s->cb->freeMemory(s);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDefined, fmi2Real tol,
                               fmi2Real start, fmi2Boolean stopDefined, fmi2Real stop)
{
    Inst *s = (Inst *)c;
    (void)stopDefined; (void)stop;
    if (tolDefined && tol > 0) s->tol = tol;
    s->time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c)
{
    reset((Inst *)c);
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real value[])
{
    Inst *s = (Inst *)c;
    double dx[DIM(NX)], y[DIM(NY)];
    int have_dx = 0, have_y = 0;
    for (size_t i = 0; i < n; ++i) {
        fmi2ValueReference r = vr[i];
        if (r < VR_X) value[i] = s->theta[r];
        else if (r < VR_DX) value[i] = s->x[r - VR_X];
        else if (r < VR_U) {
            if (!have_dx) { bg_f(s->x, s->u, s->theta, dx); have_dx = 1; }
            value[i] = dx[r - VR_DX];
        } else if (r < VR_Y) value[i] = s->u[r - VR_U];
        else if (r < VR_END) {
            if (!have_y) { bg_h(s->x, s->u, s->theta, y); have_y = 1; }
            value[i] = y[r - VR_Y];
        } else return bad_vr(s, r, "fmi2GetReal");
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       const fmi2Real value[])
{
    Inst *s = (Inst *)c;
    for (size_t i = 0; i < n; ++i) {
        fmi2ValueReference r = vr[i];
        if (r < VR_X) s->theta[r] = value[i];
        else if (r < VR_DX) s->x[r - VR_X] = value[i];
        else if (r >= VR_U && r < VR_Y) s->u[r - VR_U] = value[i];
        else return bad_vr(s, r, "fmi2SetReal");
    }
    return fmi2OK;
}

static fmi2Status no_variables(fmi2Component c, size_t n, const char *what)
{
    if (n == 0) return fmi2OK;
    logmsg((Inst *)c, fmi2Error, what);
    return fmi2Error;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[])
{ (void)vr; (void)v; return no_variables(c, n, "the model has no Integer variables"); }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[])
{ (void)vr; (void)v; return no_variables(c, n, "the model has no Boolean variables"); }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[])
{ (void)vr; (void)v; return no_variables(c, n, "the model has no String variables"); }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          const fmi2Integer v[])
{ (void)vr; (void)v; return no_variables(c, n, "the model has no Integer variables"); }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          const fmi2Boolean v[])
{ (void)vr; (void)v; return no_variables(c, n, "the model has no Boolean variables"); }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                         const fmi2String v[])
{ (void)vr; (void)v; return no_variables(c, n, "the model has no String variables"); }

static fmi2Status unsupported(fmi2Component c, const char *what)
{
    logmsg((Inst *)c, fmi2Error, what);
    return fmi2Error;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *st)
{ (void)st; return unsupported(c, "fmi2GetFMUstate is not supported"); }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate st)
{ (void)st; return unsupported(c, "fmi2SetFMUstate is not supported"); }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *st)
{ (void)st; return unsupported(c, "fmi2FreeFMUstate is not supported"); }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate st, size_t *size)
{ (void)st; (void)size; return unsupported(c, "FMU state serialisation is not supported"); }
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate st, fmi2Byte b[], size_t size)
{ (void)st; (void)b; (void)size; return unsupported(c, "FMU state serialisation is not supported"); }
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t size, fmi2FMUstate *st)
{ (void)st; (void)b; (void)size; return unsupported(c, "FMU state serialisation is not supported"); }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz,
                                        const fmi2Real dv[], fmi2Real dz[])
{
    (void)u; (void)nu; (void)z; (void)nz; (void)dv; (void)dz;
    return unsupported(c, "fmi2GetDirectionalDerivative is not supported");
}

/* ------------------------------------------------------ model exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info)
{
    (void)c;
    info->newDiscreteStatesNeeded = fmi2False;
    info->terminateSimulation = fmi2False;
    info->nominalsOfContinuousStatesChanged = fmi2False;
    info->valuesOfContinuousStatesChanged = fmi2False;
    info->nextEventTimeDefined = fmi2False;
    info->nextEventTime = 0.0;
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminate)
{
    (void)c; (void)noSetFMUStatePriorToCurrentPoint;
    *enterEventMode = fmi2False;
    *terminate = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time)
{
    ((Inst *)c)->time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx)
{
    Inst *s = (Inst *)c;
    if (nx != (size_t)NX) return unsupported(c, "fmi2SetContinuousStates: wrong number of states");
    for (size_t i = 0; i < nx; ++i) s->x[i] = x[i];
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx)
{
    Inst *s = (Inst *)c;
    double d[DIM(NX)];
    if (nx != (size_t)NX) return unsupported(c, "fmi2GetDerivatives: wrong number of states");
    bg_f(s->x, s->u, s->theta, d);
    for (size_t i = 0; i < nx; ++i) {
        if (!isfinite(d[i])) return unsupported(c, "fmi2GetDerivatives: a derivative is not finite");
        dx[i] = d[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t nz)
{ (void)z; return no_variables(c, nz, "the model has no event indicators"); }

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx)
{
    Inst *s = (Inst *)c;
    if (nx != (size_t)NX) return unsupported(c, "fmi2GetContinuousStates: wrong number of states");
    for (size_t i = 0; i < nx; ++i) x[i] = s->x[i];
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real nominal[], size_t nx)
{
    (void)c;
    for (size_t i = 0; i < nx; ++i) nominal[i] = 1.0;
    return fmi2OK;
}

/* -------------------------------------------------------- co-simulation */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real value[])
{ (void)vr; (void)order; (void)value; return no_variables(c, n, "input derivatives are not supported"); }
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer order[], fmi2Real value[])
{ (void)vr; (void)order; (void)value; return no_variables(c, n, "output derivatives are not supported"); }

/* Dormand-Prince 5(4) coefficients (Hairer, Norsett, Wanner 1993, table 5.2) */
static const double A21 = 1.0 / 5, A31 = 3.0 / 40, A32 = 9.0 / 40, A41 = 44.0 / 45,
    A42 = -56.0 / 15, A43 = 32.0 / 9, A51 = 19372.0 / 6561, A52 = -25360.0 / 2187,
    A53 = 64448.0 / 6561, A54 = -212.0 / 729, A61 = 9017.0 / 3168, A62 = -355.0 / 33,
    A63 = 46732.0 / 5247, A64 = 49.0 / 176, A65 = -5103.0 / 18656, B1 = 35.0 / 384,
    B3 = 500.0 / 1113, B4 = 125.0 / 192, B5 = -2187.0 / 6784, B6 = 11.0 / 84,
    E1 = 71.0 / 57600, E3 = -71.0 / 16695, E4 = 71.0 / 1920, E5 = -17253.0 / 339200,
    E6 = 22.0 / 525, E7 = -1.0 / 40;

/* one trial step of size h from s->x: the 5th-order solution into xn (and
 * its derivative into k7), the scaled RMS error estimate returned */
static double dopri_trial(Inst *s, double h, const double *k1, double *xn, double *k7)
{
    double k2[DIM(NX)], k3[DIM(NX)], k4[DIM(NX)], k5[DIM(NX)], k6[DIM(NX)], z[DIM(NX)];
    const double *x = s->x, *u = s->u, *p = s->theta;
    int i;
    for (i = 0; i < NX; ++i) z[i] = x[i] + h * A21 * k1[i];
    bg_f(z, u, p, k2);
    for (i = 0; i < NX; ++i) z[i] = x[i] + h * (A31 * k1[i] + A32 * k2[i]);
    bg_f(z, u, p, k3);
    for (i = 0; i < NX; ++i) z[i] = x[i] + h * (A41 * k1[i] + A42 * k2[i] + A43 * k3[i]);
    bg_f(z, u, p, k4);
    for (i = 0; i < NX; ++i)
        z[i] = x[i] + h * (A51 * k1[i] + A52 * k2[i] + A53 * k3[i] + A54 * k4[i]);
    bg_f(z, u, p, k5);
    for (i = 0; i < NX; ++i)
        z[i] = x[i] + h * (A61 * k1[i] + A62 * k2[i] + A63 * k3[i] + A64 * k4[i] + A65 * k5[i]);
    bg_f(z, u, p, k6);
    for (i = 0; i < NX; ++i)
        xn[i] = x[i] + h * (B1 * k1[i] + B3 * k3[i] + B4 * k4[i] + B5 * k5[i] + B6 * k6[i]);
    bg_f(xn, u, p, k7);
    double err = 0.0;
    for (i = 0; i < NX; ++i) {
        double e = h * (E1 * k1[i] + E3 * k3[i] + E4 * k4[i] + E5 * k5[i] + E6 * k6[i]
                        + E7 * k7[i]);
        double sc = s->tol * fmax(fabs(x[i]), fabs(xn[i])) + s->tol * 1e-6 + DBL_MIN;
        err += (e / sc) * (e / sc);
        if (!isfinite(xn[i])) return INFINITY;
    }
    return sqrt(err / (NX > 0 ? NX : 1));
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real H, fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    Inst *s = (Inst *)c;
    double k1[DIM(NX)], k7[DIM(NX)], xn[DIM(NX)];
    double tend = t + H, tt = t;
    long steps = 0;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (H < 0) return unsupported(c, "fmi2DoStep: negative communication step");
    if (NX == 0 || H == 0) { s->time = tend; return fmi2OK; }
    double h = s->h > 0 ? fmin(s->h, H) : H * 1e-3;
    bg_f(s->x, s->u, s->theta, k1);
    while (tend - tt > 1e-14 * fmax(1.0, fabs(tend))) {
        if (++steps > MAX_STEPS)
            return unsupported(c, "fmi2DoStep: too many internal steps" BG_STEP_HINT);
        int last = tt + h >= tend;
        double hh = last ? tend - tt : h;
        double err = dopri_trial(s, hh, k1, xn, k7);
        if (err <= 1.0) {
            tt = last ? tend : tt + hh;
            memcpy(s->x, xn, sizeof(double) * NX);
            memcpy(k1, k7, sizeof(double) * NX);   /* first same as last */
        }
        double fac = err > 0 ? 0.9 * pow(err, -0.2) : 5.0;
        fac = fmin(5.0, fmax(0.2, isfinite(fac) ? fac : 0.2));
        h = hh * fac;
        if (h < 1e-14 * fmax(1.0, fabs(tt)))
            return unsupported(c, "fmi2DoStep: step size underflow (a state is not finite?)"
                               BG_STEP_HINT);
        if (err <= 1.0 && !last) s->h = h;
    }
    s->time = tend;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { return unsupported(c, "fmi2CancelStep: steps are synchronous"); }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind k, fmi2Status *v)
{ (void)k; (void)v; return unsupported(c, "fmi2GetStatus: steps are synchronous"); }
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind k, fmi2Real *v)
{
    if (k == fmi2LastSuccessfulTime) { *v = ((Inst *)c)->time; return fmi2OK; }
    return unsupported(c, "fmi2GetRealStatus: only fmi2LastSuccessfulTime");
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind k, fmi2Integer *v)
{ (void)k; (void)v; return unsupported(c, "fmi2GetIntegerStatus is not supported"); }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind k, fmi2Boolean *v)
{ (void)k; (void)v; return unsupported(c, "fmi2GetBooleanStatus is not supported"); }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind k, fmi2String *v)
{ (void)k; (void)v; return unsupported(c, "fmi2GetStringStatus is not supported"); }
