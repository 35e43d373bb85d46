#pragma once
// The thermal half of characterization: which recording serves which thermal parameter, and the choice of
// R_th among the estimates that the data support.
//  - C_th: rest cooling (thesis eq. 4.7 integrated over chunks of the rests: energy balance, no differentiated
//    temperature in the regressor) over the long rests of every recording with heat flux, in one regression.
//  - dU/dT by SOC: the longest CC discharge that is not part of an HPPC (thesis eqs. 4.4-4.6).
//  - R_th: three estimates are computed and reported: (a) heat flux against T - T_amb, (b) the cooling time
//    constant of rests over C_th, (c) the value that best reproduces the measured surface temperature of the
//    characterization recordings when the thermal model is driven by the measured heat generation
//    I*(V - OCV) + I*T*dU/dT (C_th and dU/dT held). The model uses (c): it is the estimate that reproduces the
//    temperature, which is what the model predicts, without resting on the heat flux sensor's calibration or
//    on its patch standing for the whole surface, and without inheriting the electrical model's errors;
//    (a) and (b) stay in the summary and disagreements are noted.
#include <vector>

#include "cellbench/core/recording.hpp"
#include "cellbench/estimator/fit.hpp"
#include "cellbench/estimator/segment.hpp"

namespace cellbench::estimator {

// electrical: a parameter set whose electrical tables and capacity are final (its thermal part is ignored).
// soc_of_row: SOC of every row per recording where the caller knows it (Coulomb counting from a full
// charge); an empty entry means "from the state the recording implies" (first voltage less the ohmic drop).
ThermalCharacterization fit_thermal_parameters(const std::vector<Recording>& recordings,
                                               const std::vector<RecordingSegments>& segments,
                                               const std::vector<std::vector<double>>& soc_of_row,
                                               const ParameterSet& electrical, const CharacterizationOptions& options);

}  // namespace cellbench::estimator
